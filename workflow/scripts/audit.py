"""Leakage audit: `audit_report` runs every check read-only and writes the report, whatever the verdict; `audit` (a
target without output, which Snakemake runs on every call) audits afresh, rewrites the same report and exits 1 when
any check fails, printing each finding."""
import logging
import sys
from pathlib import Path

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (injected by Snakemake)
logging.basicConfig(stream=sys.stderr, level=logging.INFO, format="%(message)s")

from audits.report import to_markdown, write_report
from audits.runner import run_audit
from dswm.settings import Settings, read_param

p = snakemake.params  # noqa: F821
report = run_audit(root=Path.cwd(), settings=Settings.from_plain(read_param(p.settings)),
                   extra_reads=[Path(f) for f in p.configfiles.value])
out = snakemake.output if snakemake.rule == "audit_report" else p  # noqa: F821 (`audit` has no output: params)
write_report(report, json_path=out.json, md_path=out.md)
print(to_markdown(report).split("## Evidence")[0], file=sys.stderr)
if snakemake.rule == "audit":  # noqa: F821
    failing = [f"{c['id']}: {m}" for c in report["checks"] if not c["passed"] for m in c["failures"]]
    for line in failing:
        print(f"audit FAIL {line}", file=sys.stderr)
        print(f"audit FAIL {line}", file=sys.__stderr__)
    if not report["passed"]:
        print(f"leakage audit failed ({len(failing)} findings); see {out.json} and {out.md}", file=sys.__stderr__)
        sys.exit(1)
    print(f"leakage audit passed: every check is green ({out.json})", file=sys.stderr)
