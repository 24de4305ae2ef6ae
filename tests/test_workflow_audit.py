"""The audit's place in the DAG (dry runs in an empty working directory): an existing calibration record is an
input of `audit_report`, so a calibrate job that would replace it runs first."""
from __future__ import annotations

import re
import shutil
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
    shutil.copy(ROOT / "config.yaml", tmp_path / "config.yaml")
    inputs, text = audit_inputs(tmp_path)
    assert RECORD not in inputs and not re.search(r"^rule calibrate:", text, flags=re.M)
    (tmp_path / RECORD).parent.mkdir(parents=True)
    (tmp_path / RECORD).write_text("{}")
    inputs, text = audit_inputs(tmp_path)
    assert inputs[-1] == RECORD
    assert text.index("rule calibrate:") < text.index("rule audit_report:")
