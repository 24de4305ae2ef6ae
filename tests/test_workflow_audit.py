"""The audit's place in the DAG (dry runs in an empty working directory): with u a number in config.yaml, an
existing calibration record is an input of `audit_report`, so a calibrate job that would replace it runs first.
(With `demand_intensity: calibrate` the record is always an input: tests/test_intensity.py.)"""
from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RECORD = "results/calibration/demand_intensity.json"


def audit_inputs(workdir: Path) -> tuple[list[str], str]:
    out = subprocess.run([str(Path(sys.executable).parent / "snakemake"), "-n", "--forceall", "--nolock",
                          "--cores", "2", "audit_report", "--snakefile", str(ROOT / "Snakefile"),
                          "--directory", str(workdir), "--config", "profile=smoke"],
                         cwd=workdir, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stdout + out.stderr
    block = re.search(r"^rule audit_report:\n\s+input: ([^\n]*)", out.stdout, flags=re.M)
    return block.group(1).split(", "), out.stdout


def test_the_calibration_record_is_an_audit_input_only_when_it_exists(tmp_path):
    config = re.subn(r"(?m)^  demand_intensity: .*$", "  demand_intensity: 65.58",
                     (ROOT / "config.yaml").read_text())
    assert config[1] == 1
    (tmp_path / "config.yaml").write_text(config[0])
    inputs, text = audit_inputs(tmp_path)
    assert RECORD not in inputs and not re.search(r"^rule calibrate:", text, flags=re.M)
    (tmp_path / RECORD).parent.mkdir(parents=True)
    (tmp_path / RECORD).write_text("{}")
    inputs, text = audit_inputs(tmp_path)
    assert inputs[-1] == RECORD
    assert text.index("rule calibrate:") < text.index("rule audit_report:")


def rule_inputs(workdir: Path, target: str) -> dict[str, list[str]]:
    """{rule: its first job's inputs} of a forced dry run of ``target`` in ``workdir`` (smoke profile)."""
    out = subprocess.run([str(Path(sys.executable).parent / "snakemake"), "-n", "--forceall", "--nolock",
                          "--cores", "2", target, "--snakefile", str(ROOT / "Snakefile"),
                          "--directory", str(workdir), "--config", "profile=smoke"],
                         cwd=workdir, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stdout + out.stderr
    found: dict[str, list[str]] = {}
    for rule, inputs in re.findall(r"^(?:local)?rule (\w+):\n\s+input: ([^\n]*)", out.stdout, flags=re.M):
        found.setdefault(rule, inputs.split(", "))
    return found


def test_the_probe_files_are_inputs_of_the_probe_audit_and_figures_never_of_the_tables(tmp_path):
    """`figures` writes the probe files; were they inputs of the main audit, a finished tree would rerun
    audit_report, build_tables and tables after `figures`. They are inputs of `audit_probes` alone (and of the
    `audit` target once they exist), whose report `figures` needs."""
    (tmp_path / "config.yaml").write_text((ROOT / "config.yaml").read_text())
    probe = "results/probes/milan/dswm/seed0/probe.parquet"
    (tmp_path / probe).parent.mkdir(parents=True)
    (tmp_path / probe).write_bytes(b"")  # a probe file `figures` wrote
    tables = rule_inputs(tmp_path, "tables")
    figures = rule_inputs(tmp_path, "figures")
    audit = rule_inputs(tmp_path, "audit")
    assert not [p for inputs in tables.values() for p in inputs if p.startswith("results/probes/")]
    assert not [p for p in figures["audit_report"] if p.startswith("results/probes/")]
    assert probe in figures["audit_probes"] and "results/milan/greedy/seed0/days.parquet" in figures["audit_probes"]
    assert "results/audit/probes.json" in figures["figures"] and "results/audit/report.json" not in figures["figures"]
    assert probe in audit["audit"]
