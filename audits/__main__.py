"""Command line: `python -m audits [--root DIR] [--config config.yaml] [--profile NAME] [--out DIR]`.

Reads the config file, selects the profile, resolves the settings once (dswm.settings.resolve), runs the audit
outside Snakemake, writes report.json and report.md into its own directory (default <root>/results/audit/cli/,
never the workflow's results/audit/report.json, which the tables rule is gated on), and exits 1 when any check
fails (2 when the config is invalid).
"""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from audits.report import to_markdown, write_report
from audits.runner import run_audit

CLI_OUT = "results/audit/cli"
"""Where the command line writes its report unless told otherwise: beside, not over, the workflow's report."""


def main(argv: list[str] | None = None) -> int:
    """Runs the audit; returns the exit status (0 pass, 1 a check failed, 2 the config is invalid)."""
    from dswm.config import ConfigError, load_yaml
    from dswm.settings import resolve

    ap = argparse.ArgumentParser(prog="python -m audits", description=__doc__.splitlines()[0])
    ap.add_argument("--root", default=".", help="the workflow's working directory (holds results/)")
    ap.add_argument("--config", default="config.yaml", help="config file the pipeline ran under (YAML or JSON)")
    ap.add_argument("--profile", default=None, help="override the config's profile (as --config profile=NAME)")
    ap.add_argument("--out", default=None, help=f"report directory (default: <root>/{CLI_OUT})")
    args = ap.parse_args(argv)

    root = Path(args.root)
    cfg_path = Path(args.config) if Path(args.config).is_absolute() else root / args.config
    try:
        config = load_yaml(cfg_path)
        if args.profile:
            config["profile"] = args.profile
        settings = resolve(config)
    except ConfigError as exc:
        sys.stderr.write(f"{exc}\n")
        return 2
    report = run_audit(root=root, settings=settings, extra_reads=[cfg_path])
    out = Path(args.out) if args.out else root / CLI_OUT
    write_report(report, json_path=out / "report.json", md_path=out / "report.md")
    if not report["passed"]:
        sys.stderr.write(to_markdown(report).split("## Evidence")[0])
    return 0 if report["passed"] else 1


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    sys.exit(main())
