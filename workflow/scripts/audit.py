"""Leakage audit: `audit_report` runs every check read-only over the tables' sources and writes the report, whatever
the verdict; `audit_probes` does the same for the probe files (protocol.probes_out_of_tables), `audit_extra` for the
figures' extra runs (protocol.extra_runs) and `audit_learning` for the learning runs (protocol.learning_days); `audit`
(a target without output, which Snakemake runs on every call) runs them afresh (each part when its files exist),
rewrites their reports and exits 1 when any check fails, printing each finding."""
import logging
import sys
from pathlib import Path

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (injected by Snakemake)
logging.basicConfig(stream=sys.stderr, level=logging.INFO, format="%(message)s")

from audits.report import to_markdown, write_report
from audits.runner import run_audit
from dswm.settings import Settings, read_param

p = snakemake.params  # noqa: F821
settings = Settings.from_plain(read_param(p.settings))
reads = [Path(f) for f in p.configfiles.value]
if snakemake.rule == "audit":  # noqa: F821 (`audit` has no output: its reports are named in params)
    probed = list(getattr(snakemake.input, "probes", []))  # noqa: F821 (the probe files present)
    learned = list(getattr(snakemake.input, "learning", []))  # noqa: F821 (the learning runs' files present)
    extra = list(getattr(snakemake.input, "extra", []))  # noqa: F821 (the figures' extra runs' files present)
    runs = ([("tables", p.json, p.md)] + ([("probes", p.probes_json, p.probes_md)] if probed else [])
            + ([("extra", p.extra_json, p.extra_md)] if extra else [])
            + ([("learning", p.learning_json, p.learning_md)] if learned else []))
else:
    runs = [(p.scope, snakemake.output.json, snakemake.output.md)]  # noqa: F821
failed = []
for scope, json_path, md_path in runs:
    report = run_audit(root=Path.cwd(), settings=settings, extra_reads=reads, scope=scope,
                       extra_runs=getattr(p, "extra_runs", None))  # the figures' extra runs (audit_extra, audit)
    write_report(report, json_path=json_path, md_path=md_path)
    print(to_markdown(report).split("## Evidence")[0], file=sys.stderr)
    if not report["passed"]:
        failed.append((json_path, md_path))
    for line in [f"{c['id']}: {m}" for c in report["checks"] if not c["passed"] for m in c["failures"]]:
        if snakemake.rule == "audit":  # noqa: F821
            print(f"audit FAIL {line}", file=sys.stderr)
            print(f"audit FAIL {line}", file=sys.__stderr__)
if snakemake.rule == "audit":  # noqa: F821
    if failed:
        where = "; ".join(f"{j} and {m}" for j, m in failed)
        print(f"leakage audit failed; see {where}", file=sys.__stderr__)
        sys.exit(1)
    print(f"leakage audit passed: every check is green ({', '.join(str(r[1]) for r in runs)})", file=sys.stderr)
