"""The smoke DAG on the loopback SLURM cluster, started in the background when the test session starts.

With ``pytest --cluster`` the session starts the engines (engines.py) and this run first, then the local smoke run
(conftest.local_smoke), so that their jobs use the core that the unit tests, one process, leave idle. This run is bound
by SLURM's status queries more than by its cores (its jobs' scripts used ~300 of its ~1,000 s): beside the local run it
leaves room. (The whole smoke DAG of three datasets on SLURM beside the local run did not end in 27 min; Milan's is a
third of it.) The cluster tests, which pytest runs after the unit tests, read this run's record. Without ``--cluster``
nothing here runs.

It runs the smoke DAG of ONE dataset, Milan (the main table's, the only one every method runs on, and the
calibration's), with seven of its methods (METHODS): 15 SLURM jobs, every rule of the targets among them, where all
methods of the three datasets would be 75, each with SLURM's fixed cost (~12 s of a core for its Snakemake and its
start, docs/CLUSTER.md).

The tracking server asks for credentials (basic-auth): Snakemake runs with the writer's user and password in its
environment (``MLFLOW_TRACKING_USERNAME`` / ``MLFLOW_TRACKING_PASSWORD``), which SLURM passes to every job
(``sbatch --export=ALL``), never on a command line. Every SLURM log is kept (``--slurm-keep-successful-logs``), and
while the run goes the process list is read every second (:class:`ProcessWatch`), so that the cluster tests can check
that no secret of the engines shows in a log or in ``ps``.
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
from smoke import command, copy_tree, progress

TARGETS = ("tables", "calibrate")
DATASETS = ("milan",)
"""The datasets of the SLURM run: `profiles.smoke.datasets` of the config file it adds (OVERLAY), a subset of the
local smoke run's, whose jobs have the same settings slices (no train or evaluate job reads the dataset list)."""
METHODS = ("dswm", "dswm_plus", "greedy", "ppo", "jtoratc", "static", "perfect")
"""The methods of the SLURM run: `methods.run` of OVERLAY, in config.yaml's order. One of each kind of job the cluster
tests look at: a deployment (static), the shared BCD search (greedy) and a clairvoyant bound on it (perfect), a solver
whose results carry its solve times (jtoratc), a Stable-Baselines3 learner (ppo: a train job), the world model
(dswm: a train job) and a method that evaluates another's training (dswm_plus), and the room footnote's low, high and
fill methods. Each job's settings slice is the same as in the local run (no train or evaluate job reads the method
list), so their results are compared; the other twelve methods are more of the same two rules, each with SLURM's
~17 s of a core of fixed cost (its Snakemake's parse, the job's start, accounting and the tracking server)."""
OVERLAY = "slurm_smoke.yaml"
"""Written at the root of the SLURM run's tree and given to Snakemake with ``--configfile`` after config.yaml."""
LIMIT_S = 2400
"""The hang guard of the SLURM run, not a budget: with all 18 methods (33 jobs) it took 12.8 min on this project's
2-core machine with another smoke run beside it, 16-17 min beside the unit tests, ~21 min beside both (the whole
smoke DAG's 75 took 15.1 min alone, and had not ended after 27 min beside the local run)."""
PS_EVERY_S = 1.0
"""How often the process list is read during the run (:class:`ProcessWatch`)."""
INIT_STATUS_CHECK_S = 2
"""The first `sacct` query this long after a submission: the loopback cluster's accounting answers at once, where
profiles/slurm's 10 s spare a real cluster's slurmdbd."""


@dataclass
class ProcessWatch:
    """Reads every process's command line (``ps -eww -o pid=,args=``) every ``every_s`` seconds until stopped, and
    keeps the lines that hold one of ``secrets`` (each secret shown as ``***``) and how many listings it took."""

    secrets: list[str]
    every_s: float = PS_EVERY_S
    listings: int = 0
    job_lines: int = 0
    """Lines of SLURM job steps' Snakemake (``--target-jobs``) seen: proof that the listings saw the jobs."""
    leaks: list[str] = field(default_factory=list)
    _stop: threading.Event = field(default_factory=threading.Event)

    def start(self) -> "ProcessWatch":
        threading.Thread(target=self._loop, name="ps-watch", daemon=True).start()
        return self

    def _loop(self) -> None:
        while not self._stop.is_set():
            listing = subprocess.run(["ps", "-eww", "-o", "pid=,args="], capture_output=True, text=True).stdout
            self.listings += 1
            for line in listing.splitlines():
                self.job_lines += "--target-jobs" in line
                if any(secret in line for secret in self.secrets):
                    shown = line
                    for secret in self.secrets:
                        shown = shown.replace(secret, "***")
                    self.leaks.append(shown.strip())
            self._stop.wait(self.every_s)

    def stop(self) -> None:
        self._stop.set()


@dataclass
class SlurmSmokeRun:
    """`snakemake tables calibrate --executor slurm --profile profiles/slurm --jobs 4` on DATASETS in a fresh copy of
    the tree under ``root``, logging to the loopback MLflow server; stopped when it runs past ``limit_s``."""

    root: Path
    engines: LoopbackEngines | None = None
    error: str | None = None
    proc: subprocess.Popen | None = None
    work: Path | None = None
    log: Path | None = None
    started: float = 0.0
    ended: float | None = None
    argv: list[str] = field(default_factory=list)
    limit_s: float = LIMIT_S
    overrun: str | None = None
    ps: ProcessWatch | None = None

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
            (self.work / OVERLAY).write_text("# the SLURM smoke run of the cluster tests (cluster/background.py)\n"
                                             f"profiles: {{smoke: {{datasets: [{', '.join(DATASETS)}]}}}}\n"
                                             f"methods: {{run: [{', '.join(METHODS)}]}}\n")
            self.argv, env = command(*TARGETS, "--configfile", OVERLAY,
                                     "--executor", "slurm", "--profile", "profiles/slurm", "--jobs", "4",
                                     "--slurm-init-seconds-before-status-checks", str(INIT_STATUS_CHECK_S),
                                     "--slurm-keep-successful-logs",
                                     config=[f"mlflow={{tracking_uri: '{self.engines.mlflow_uri}'}}"],
                                     env=self.engines.credentials)
            self.ps = ProcessWatch(secrets=self.engines.secrets()).start()
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
        """Record when the run ends (its wall time), whenever the tests come to read it; stop reading ``ps`` then."""
        self.proc.wait()
        self.ended = time.monotonic()
        self.ps.stop()

    def settle(self) -> None:
        """Return once the run has ended, or once it has run ``limit_s`` (then it is stopped and ``overrun`` says how
        far it got); never raises, so that the local smoke run can follow it whatever became of it."""
        if self.proc is None:
            return
        try:
            self.proc.wait(timeout=max(1.0, self.started + self.limit_s - time.monotonic()))
        except subprocess.TimeoutExpired:
            self.overrun = (f"the SLURM smoke run (`snakemake {' '.join(self.argv[1:])}` in {self.work}) did not end "
                            f"within {self.limit_s:.0f} s (its hang guard, tests/cluster/background.py LIMIT_S): "
                            f"{progress(self.log.read_text(errors='replace'))} when it was stopped; its output: "
                            f"{self.log}")
            self.end_run()

    def wait(self) -> tuple[int, str, float]:
        """Wait for the run's end: its exit code, its output and its wall time in seconds; raises when it did not
        start or ran past its hang guard."""
        if self.error is not None:
            raise RuntimeError(f"the SLURM smoke run did not start:\n{self.error}")
        self.settle()
        if self.overrun is not None:
            raise RuntimeError(self.overrun)
        while self.ended is None:  # the watcher sets it as the process ends
            time.sleep(0.05)
        return self.proc.returncode, self.log.read_text(errors="replace"), self.ended - self.started

    def stop(self) -> None:
        """End the run if it still goes, then stop the engines."""
        self.end_run()
        if self.ps is not None:
            self.ps.stop()
        if self.engines is not None:
            self.engines.stop()

    def end_run(self) -> None:
        """End the run if it still goes (Snakemake cancels its SLURM jobs on SIGTERM); the engines keep running."""
        if self.proc is not None and self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout=60)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=10)
