"""The `figures` and `learning` targets: what they drew rests on a passing audit of the files as they are now.

Runs on every `snakemake figures` or `snakemake learning` (targets without output), after their figures and their parts
of the leakage audit: `audit_probes` and `audit_extra` for `figures` (no probe number reached a table's source; the
extra runs evaluated models trained on training days, unchanged), `audit_learning` for `learning` (the curves score
held-out training days only). The gate of the tables is applied to each report: it passed, audits this profile and
these settings, and every file it vouches for hashes as the audit found it. Otherwise the call fails with the reasons.
"""
import sys
from pathlib import Path

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (injected by Snakemake)

from audits.runner import gate
from dswm.settings import read_param

target = snakemake.params.target  # noqa: F821 ("figures" or "learning")
reports = snakemake.input.report  # noqa: F821 (one report, or a list of them)
reports = [reports] if isinstance(reports, str) else list(reports)
expect = read_param(snakemake.params.audit)  # noqa: F821
refusals = [line for r in reports for line in gate(r, expect=expect, root=Path.cwd(), target=target)]
if refusals:
    for line in refusals:
        print(f"{target} refused: {line}", file=sys.stderr)
        print(f"{target} refused: {line}", file=sys.__stderr__)
    sys.exit(1)
print(f"{target}: {' and '.join(map(str, reports))} passed; every file they vouch for is as audited", file=sys.stderr)
