"""The smoke-profile run of the whole DAG that the integration and cluster tests share: a copy of the working tree,
and Snakemake called in it as a user would."""
from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SKIP = {".git", ".venv", "results", "logs", ".snakemake", "__pycache__", ".pytest_cache", ".hypothesis", "build"}
TIMING = "smoke_timing.json"
"""Written at the root of the smoke tree: the wall time of each of its Snakemake calls, in seconds."""
LIMIT_S = 2400
"""The hang guard of one call of the smoke DAG (`tables calibrate`, then `figures`), not a budget: on this project's
2-core machine `tables calibrate` takes 7 min idle and took 17.7 min with another smoke run beside it; the slowest
call measured, 22.2 min, ran beside the whole smoke DAG on SLURM, which the cluster tests now run before the local
run rather than beside it (conftest.smoke_tables)."""
PROGRESS = re.compile(r"^(\d+) of (\d+) steps \((\d+%)\) done", flags=re.M)


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


def progress(text: str) -> str:
    """How far a Snakemake run got, from its output: its last "N of M steps (P%) done" line."""
    found = PROGRESS.findall(text)
    if not found:
        return "no job had finished"
    done, total, percent = found[-1]
    return f"{done} of {total} steps ({percent}) done"


def run_smoke(work: Path, name: str, *targets: str, limit_s: float = LIMIT_S) -> Path:
    """The smoke DAG's ``targets`` in ``work`` with ``--cores 2``; the call's output goes to ``smoke_<name>.out`` at
    the root of ``work``, its wall time to TIMING under ``name``. A call that fails, or runs past ``limit_s`` (then
    it is stopped), raises naming the call, the tree and how far it got."""
    argv, env = command(*targets, "--cores", "2")
    log = work / f"smoke_{name}.out"
    what = f"the local smoke run `snakemake {' '.join(targets)} --cores 2` in {work}"
    start = time.monotonic()
    with open(log, "wb") as out:
        proc = subprocess.Popen(argv, cwd=work, env=env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        rc = proc.wait(timeout=limit_s)
    except subprocess.TimeoutExpired:
        stop(proc)
        raise AssertionError(f"{what} did not end within {limit_s:.0f} s (its hang guard, tests/smoke.py LIMIT_S): "
                             f"{progress(log.read_text(errors='replace'))} when it was stopped; its output: {log}")
    wall = round(time.monotonic() - start, 1)
    text = log.read_text(errors="replace")
    assert rc == 0, f"{what} exited with {rc} after {wall} s, {progress(text)}; its output ({log}):\n{text[-8000:]}"
    timing = json.loads((work / TIMING).read_text()) if (work / TIMING).exists() else {}
    (work / TIMING).write_text(json.dumps({**timing, name: wall}))
    return work


def stop(proc: subprocess.Popen, grace: float = 60.0) -> None:
    """End a process started in its own session (a local Snakemake run and its jobs, an engine): SIGTERM to its
    process group, SIGKILL after ``grace`` seconds."""
    if proc.poll() is not None:
        return
    with contextlib.suppress(ProcessLookupError):
        os.killpg(proc.pid, signal.SIGTERM)
    try:
        proc.wait(timeout=grace)
    except subprocess.TimeoutExpired:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)
