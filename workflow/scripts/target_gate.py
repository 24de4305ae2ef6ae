"""The `figures` and `learning` targets: what they drew rests on a passing audit of the files as they are now.

Runs on every `snakemake figures` or `snakemake learning` (targets without output), after their figures and their part
of the leakage audit: `audit_probes` for `figures` (no probe number reached a table's source), `audit_learning` for
`learning` (the curves score held-out training days only). The gate of the tables is applied to that report: it
passed, audits this profile and these settings, and every file it vouches for hashes as the audit found it.
Otherwise the call fails with the reasons.
"""
import sys
from pathlib import Path

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (injected by Snakemake)

from audits.runner import gate
from dswm.settings import read_param

target = snakemake.params.target  # noqa: F821 ("figures" or "learning")
what = {"figures": "the probe audit", "learning": "the learning audit"}[target]
report = snakemake.input.report  # noqa: F821
refusals = gate(report, expect=read_param(snakemake.params.audit), root=Path.cwd(), target=target)  # noqa: F821
if refusals:
    for line in refusals:
        print(f"{target} refused: {line}", file=sys.stderr)
        print(f"{target} refused: {line}", file=sys.__stderr__)
    sys.exit(1)
print(f"{target}: {what} {report} passed and vouches for every file as it is now", file=sys.stderr)
