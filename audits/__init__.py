"""The read-only leakage audit of the DSWM pipeline (`snakemake --cores 2 audit`).

Three families of checks, each computed from the files alone: `audits.splits` (temporal split, evaluation
days), `audits.statistics` (normalization, intensity alignment, initial positions and calibration recomputed
from the TRAINING segment) and `audits.protocol` (identical hashes and days for every method, training
records, checkpoints). `audits.ledger` proves that nothing the audit read was changed.
"""
