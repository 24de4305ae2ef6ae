"""The smoke DAG on the loopback SLURM cluster, started in the background when the test session starts.

With ``pytest --cluster`` the session starts the engines (engines.py) and this run first, so that the SLURM jobs
use the core that the unit tests, one process, leave idle; the cluster tests, which pytest runs last, wait for its
end and read its record. Without ``--cluster`` nothing here runs.
"""
from __future__ import annotations

import contextlib
import signal
import subprocess
import threading
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path

from cluster.engines import LoopbackEngines, missing
from smoke import command, copy_tree

TARGETS = ("tables", "calibrate")
INIT_STATUS_CHECK_S = 2
"""The first `sacct` query this long after a submission: the loopback cluster's accounting answers at once, where
profiles/slurm's 10 s spare a real cluster's slurmdbd."""


@dataclass
class SlurmSmokeRun:
    """`snakemake tables calibrate --executor slurm --profile profiles/slurm --jobs 4` in a fresh copy of the tree
    under ``root``, logging to the loopback MLflow server."""

    root: Path
    engines: LoopbackEngines | None = None
    error: str | None = None
    proc: subprocess.Popen | None = None
    work: Path | None = None
    log: Path | None = None
    started: float = 0.0
    ended: float | None = None
    argv: list[str] = field(default_factory=list)

    def launch(self) -> "SlurmSmokeRun":
        """Start the engines and the run; a failure is kept in ``error`` (the cluster tests fail naming it)."""
        try:
            absent = missing()
            if absent:
                raise RuntimeError("the cluster tests need: " + "; ".join(absent) +
                                   " (install them as root: bash tests/cluster/install.sh)")
            self.engines = LoopbackEngines(root=self.root / "engines").start()
            self.work = copy_tree(self.root / "repo")
            self.log = self.root / "snakemake.out"
            self.argv, env = command(*TARGETS, "--executor", "slurm", "--profile", "profiles/slurm", "--jobs", "4",
                                     "--slurm-init-seconds-before-status-checks", str(INIT_STATUS_CHECK_S),
                                     config=[f"mlflow={{tracking_uri: '{self.engines.mlflow_uri}'}}"])
            with open(self.log, "wb") as out:
                self.started = time.monotonic()
                self.proc = subprocess.Popen(self.argv, cwd=self.work, env=env, stdout=out,
                                             stderr=subprocess.STDOUT, start_new_session=True)
            threading.Thread(target=self._watch, name="slurm-smoke-end", daemon=True).start()
        except Exception:
            self.error = traceback.format_exc()
            self.stop()
        return self

    def _watch(self) -> None:
        """Record when the run ends (its wall time), whenever the tests come to read it."""
        self.proc.wait()
        self.ended = time.monotonic()

    def wait(self, timeout: float) -> tuple[int, str, float]:
        """Wait for the run's end: its exit code, its output and its wall time in seconds."""
        if self.error is not None:
            raise RuntimeError(f"the SLURM smoke run did not start:\n{self.error}")
        try:
            rc = self.proc.wait(timeout=max(1.0, self.started + timeout - time.monotonic()))
        except subprocess.TimeoutExpired:
            self.stop()
            raise RuntimeError(f"the SLURM smoke run took more than {timeout:.0f} s; its output: {self.log}")
        while self.ended is None:  # the watcher sets it as the process ends
            time.sleep(0.05)
        return rc, self.log.read_text(errors="replace"), self.ended - self.started

    def stop(self) -> None:
        """End the run if it still goes (Snakemake cancels its SLURM jobs on SIGTERM), then stop the engines."""
        if self.proc is not None and self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=10)
        if self.engines is not None:
            self.engines.stop()
