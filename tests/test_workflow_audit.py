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
