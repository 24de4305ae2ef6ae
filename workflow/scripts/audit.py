"""Leakage audit: `audit_report` runs every check read-only and writes the report; `audit` fails on a red one."""
import logging
import sys
from pathlib import Path

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (injected by Snakemake)
logging.basicConfig(stream=sys.stderr, level=logging.INFO, format="%(message)s")

from audits.report import to_markdown, write_atomic, write_report
from audits.runner import gate, run_audit
from dswm.settings import Settings, read_param

if snakemake.rule == "audit_report":  # noqa: F821
    settings = Settings.from_plain(read_param(snakemake.params.settings))  # noqa: F821
    report = run_audit(root=Path.cwd(), settings=settings,
                       extra_reads=[Path(f) for f in snakemake.params.configfiles.value])  # noqa: F821
    write_report(report, json_path=snakemake.output.json, md_path=snakemake.output.md)  # noqa: F821
    print(to_markdown(report).split("## Evidence")[0], file=sys.stderr)
else:
    failing = gate(snakemake.input.report)  # noqa: F821
    for line in failing:
        print(f"audit FAIL {line}", file=sys.stderr)
        print(f"audit FAIL {line}", file=sys.__stderr__)
    if failing:
        print(f"leakage audit failed ({len(failing)} findings); see {snakemake.input.report} and the .md beside it",
              file=sys.__stderr__)
        sys.exit(1)
    print(f"leakage audit passed: every check of {snakemake.input.report} is green", file=sys.stderr)  # noqa: F821
    write_atomic(Path(snakemake.output.passed), "leakage audit passed: " + snakemake.input.report + "\n")  # noqa: F821
