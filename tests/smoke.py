"""The smoke-profile run of the whole DAG that the integration and cluster tests share: a copy of the working tree,
and Snakemake called in it as a user would."""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SKIP = {".git", ".venv", "results", "logs", ".snakemake", "__pycache__", ".pytest_cache", ".hypothesis", "build"}
TIMING = "smoke_timing.json"
"""Written at the root of the smoke tree: the wall time of each of its Snakemake calls, in seconds."""


def copy_tree(dest: Path) -> Path:
    """A copy of the working tree at ``dest`` without outputs, environments and committed benchmark figures."""
    shutil.copytree(ROOT, dest, ignore=lambda d, names: [n for n in names if n in SKIP or
                                                         (Path(d).name == "benchmarks" and n == "results")])
    return dest


def command(*args, profile="smoke", config=(), env=None) -> tuple[list[str], dict]:
    """The argv and environment of this environment's ``snakemake`` with ``args`` under the budget ``profile``, plus
    the ``config`` overrides (``key=value``; they go with the profile in ONE ``--config``: a second ``--config``
    would replace the first)."""
    env = {**os.environ, **(env or {}),
           "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"}
    exe = str(Path(sys.executable).parent / "snakemake")
    return [exe, *args, "--config", f"profile={profile}", *config], env


def snakemake(workdir, *args, timeout=1500, profile="smoke", env=None):
    """Run this environment's ``snakemake`` in ``workdir`` under the budget ``profile``; the completed process."""
    argv, env = command(*args, profile=profile, env=env)
    return subprocess.run(argv, cwd=workdir, env=env, capture_output=True, text=True, timeout=timeout)


def run_smoke(work: Path) -> Path:
    """The smoke DAG in ``work``: ``tables calibrate``, then ``figures``; each call's wall time goes to TIMING."""
    timing = {}
    for name, targets in (("tables", ("tables", "calibrate")), ("figures", ("figures",))):
        start = time.monotonic()
        proc = snakemake(work, *targets, "--cores", "2")
        assert proc.returncode == 0, proc.stdout[-5000:] + proc.stderr[-5000:]
        timing[name] = round(time.monotonic() - start, 1)
    (work / TIMING).write_text(json.dumps(timing))
    return work
