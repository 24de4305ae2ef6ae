"""The read-only leakage audit of the DSWM pipeline (`snakemake --cores 2 audit`).

Three families of checks, each computed from the files alone: `audits.splits` (temporal split, evaluation
days), `audits.statistics` (normalization, intensity alignment, initial positions and calibration recomputed
from the TRAINING segment) and `audits.protocol` with `audits.training` (identical hashes and days for every
method, training records, checkpoints, evaluated models). `audits.ledger` proves that nothing the audit read
was changed. The audit reads the run's typed settings (`dswm.settings.Settings`), resolved once by its caller.
"""
