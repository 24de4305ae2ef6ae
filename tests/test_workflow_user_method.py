"""The README's own method ("Your own method"), taken from the README as written: its class and its config run the
`tables` target, and only the `select` target, which tunes the DSWM planner that config leaves out, stops, with a
message that says what to change."""
from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from dswm import settings as runconfig
from dswm.config import load_yaml

ROOT = Path(__file__).resolve().parents[1]


def readme_method(dest: Path) -> Path:
    """The README's example written as ``dest/my_methods.py`` and its config as ``dest/user.yaml`` (a --configfile);
    returns the config file."""
    section = (ROOT / "README.md").read_text().split("## Your own method", 1)[1].split("\n## ", 1)[0]
    (dest / "my_methods.py").write_text(re.search(r"```python\n(.*?)```", section, flags=re.S).group(1))
    run = re.search(r"`methods\.run: (\[[^`]*\])`", section).group(1)
    user = re.search(r"`methods\.user\.hover: (\{[^`]*\})`", section).group(1)
    cfg = dest / "user.yaml"
    cfg.write_text(yaml.safe_dump({"methods": {"run": yaml.safe_load(run), "user": {"hover": yaml.safe_load(user)}}}))
    return cfg


def dry_run(target: str, cfg: Path) -> subprocess.CompletedProcess:
    """``snakemake -n target --configfile cfg`` with the example's module importable, as the README runs it."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(cfg.parent), str(ROOT / "src"), str(ROOT)])}
    return subprocess.run([str(Path(sys.executable).parent / "snakemake"), "-n", "--nolock", "--cores", "2", target,
                           "--configfile", str(cfg)], cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)


@pytest.fixture
def example(tmp_path):
    return readme_method(tmp_path)


def test_the_readme_example_is_what_the_readme_shows(example):
    cfg = load_yaml(example)
    assert cfg["methods"]["run"] == ["static", "greedy", "oracle", "hover"]
    assert cfg["methods"]["user"]["hover"] == {"class": "my_methods:Hover", "options": {"bw_logit": 0.0}}
    assert "class Hover(Controller):" in (example.parent / "my_methods.py").read_text()


def test_the_readme_example_runs_the_tables_target(example):
    proc = dry_run("tables", example)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    text = proc.stdout + proc.stderr
    default = runconfig.resolve(load_yaml(ROOT / "config.yaml"))  # the profile's datasets and seeds
    pairs = sorted((d, str(s)) for d in default.run.datasets for s in default.seeds(d))
    hover = re.findall(r"^rule evaluate:\n(?:\s+.*\n)*?\s+output: results/(\w+)/hover/seed(\d+)/days\.parquet", text,
                       flags=re.M)
    assert sorted(hover) == pairs
    counts = dict(re.findall(r"^(evaluate|train|select)\s+(\d+)$", text, flags=re.M))
    assert counts == {"evaluate": str(4 * len(pairs))}  # static, greedy, oracle, hover; none learns; no select


def test_only_the_select_target_needs_the_planner_method_and_says_so(example):
    proc = dry_run("select", example)
    assert proc.returncode != 0
    assert ("config.yaml: key 'selection.planner_method' is 'dswm', which 'methods.run' does not list (found "
            "static, greedy, oracle, hover); the select target chooses that method's planner values: add 'dswm' to "
            "'methods.run', or name a planner method of it in 'selection.planner_method'") in proc.stdout + proc.stderr
