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
import threading
import time
import traceback
from pathlib import Path
from typing import Callable

ROOT = Path(__file__).resolve().parents[1]
SKIP = {".git", ".venv", "results", "logs", ".snakemake", "__pycache__", ".pytest_cache", ".hypothesis", "build"}
TIMING = "smoke_timing.json"
"""Written at the root of the smoke tree: the wall time of each of its Snakemake calls, in seconds."""
LIMIT_S = 2400
"""The hang guard of one call of the smoke DAG (`tables calibrate`, then `figures`), not a budget: on this project's
2-core machine `tables calibrate` takes 7-11 min idle and took 17.7 min with another smoke run beside it; the
slowest call measured, 22.2 min, ran beside the whole smoke DAG of three datasets on SLURM (the cluster tests run
Milan's alone, beside it and the unit tests: conftest.local_smoke)."""
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


def run_smoke(work: Path, name: str, *targets: str, limit_s: float = LIMIT_S,
              started: Callable[[subprocess.Popen], None] | None = None, command_of: Callable | None = None) -> Path:
    """The smoke DAG's ``targets`` in ``work`` with ``--cores 2``; the call's output goes to ``smoke_<name>.out`` at
    the root of ``work``, its wall time to TIMING under ``name``. A call that fails, or runs past ``limit_s`` (then
    it is stopped), raises naming the call, the tree and how far it got. ``started`` is given the Snakemake process
    as it starts (so that a caller in another thread can stop it); ``command_of`` stands in for :func:`command`."""
    argv, env = (command_of or command)(*targets, "--cores", "2")
    log = work / f"smoke_{name}.out"
    what = f"the local smoke run `snakemake {' '.join(targets)} --cores 2` in {work}"
    start = time.monotonic()
    with open(log, "wb") as out:
        proc = subprocess.Popen(argv, cwd=work, env=env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
    if started is not None:
        started(proc)
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


class LocalSmokeRun:
    """The local smoke run in a thread of its own, started as the test session starts: `tables calibrate` in a copy
    of the working tree, then, where a collected test needs it, `figures room_fill` in the same tree
    (:func:`run_smoke` for each call). The unit tests, one process, go on beside it, and so does the SLURM run of
    the cluster tests; a test that reads the run waits for its call with :meth:`result`."""

    CALLS = {"tables": ("tables", "calibrate"), "figures": ("figures", "room_fill")}
    """The calls in their order, by name: the name of each one's output file and timing entry."""

    def __init__(self, work: Path, calls: tuple[str, ...], command_of: Callable | None = None):
        self.work, self.calls, self.command_of = work, calls, command_of
        self.done = {name: threading.Event() for name in calls}
        self.errors: dict[str, BaseException] = {}
        self.proc: subprocess.Popen | None = None
        self._cancelled = threading.Event()

    def launch(self) -> "LocalSmokeRun":
        threading.Thread(target=self._run, name="local-smoke", daemon=True).start()
        return self

    def _run(self) -> None:
        exc: BaseException | None = None
        try:
            copy_tree(self.work)
        except Exception:
            exc = RuntimeError(f"the local smoke run's tree could not be copied to {self.work}:\n"
                               f"{traceback.format_exc()}")
        for name in self.calls:
            if exc is None and self._cancelled.is_set():
                exc = RuntimeError(f"the local smoke run in {self.work} was stopped before its `{name}` call")
            if exc is None:
                try:
                    run_smoke(self.work, name, *self.CALLS[name], started=self._started,
                              command_of=self.command_of)
                except BaseException as err:  # kept for the tests that read the run; a later call needs this one
                    exc = err
            if exc is not None:
                self.errors[name] = exc
            self.done[name].set()

    def _started(self, proc: subprocess.Popen) -> None:
        self.proc = proc
        if self._cancelled.is_set():
            stop(proc)

    def result(self, name: str) -> Path:
        """The tree once the call ``name`` and those before it have run; raises their failure."""
        self.done[name].wait()
        if name in self.errors:
            raise self.errors[name]
        return self.work

    def stop(self) -> None:
        """End the run if it still goes (the session ends early, or no test came to read it)."""
        self._cancelled.set()
        if self.proc is not None:
            stop(self.proc)
