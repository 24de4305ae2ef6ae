"""The `figures` target: the figures in place rest on a passing probe audit of the files as they are now.

Runs on every `snakemake figures` (a target without output), after every figure and the `audit_probes` report. The
gate of the tables is applied to that report: it passed (no probe number reached a table's source), audits this
profile and these settings, and every file it vouches for (the probe files, the tables' sources) hashes as the audit
found it. Otherwise the call fails with the reasons.
"""
import sys
from pathlib import Path

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (injected by Snakemake)

from audits.runner import gate
from dswm.settings import read_param

report = snakemake.input.report  # noqa: F821
refusals = gate(report, expect=read_param(snakemake.params.audit), root=Path.cwd(), target="figures")  # noqa: F821
if refusals:
    for line in refusals:
        print(f"figures refused: {line}", file=sys.stderr)
        print(f"figures refused: {line}", file=sys.__stderr__)
    sys.exit(1)
print(f"figures: the probe audit {report} passed and vouches for every file as it is now", file=sys.stderr)
