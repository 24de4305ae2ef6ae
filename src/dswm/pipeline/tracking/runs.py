"""The one MLflow run of a job (:func:`job_run`, yielding a :class:`JobRun`): tagged, its settings slice as params,
metrics in batches, ended FINISHED or FAILED, earlier finished runs of its job key replaced."""
from __future__ import annotations

import contextlib
import json
import shutil
import signal
import subprocess
import threading
import time
import warnings
from pathlib import Path
from typing import Any, Iterator, Mapping, Sequence

from mlflow.entities import Metric, Param, RunStatus
from mlflow.tracking import MlflowClient

from dswm.pipeline.tracking.client import (MAX_PARAM_CHARS, MAX_PARAMS_PER_BATCH, TrackingAuthError, TrackingError,
                                           retry, uses_server, workdir_tag)
from dswm.pipeline.tracking.store import TREE_TAG, adopt_store, main_experiment, run_experiments, store_client
from prep.atomic import atomic_path


def flatten(config: Mapping[str, Any], prefix: str = "") -> dict[str, str]:
    """Dotted-key, string-valued view of a nested config (lists as JSON), ready to be MLflow params."""
    out: dict[str, str] = {}
    for key, value in config.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping) and value:
            out.update(flatten(value, name + "."))
        else:
            text = json.dumps(value) if isinstance(value, (list, dict)) else str(value)
            out[name] = text[:MAX_PARAM_CHARS]
    return out


def git_commit(repo: str | Path) -> str:
    """HEAD commit of ``repo`` (with "-dirty" when tracked files differ), or "unknown" outside git."""
    try:
        head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=repo, capture_output=True, text=True, check=True)
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=repo,
                               capture_output=True, text=True, check=True)
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
    return head.stdout.strip() + ("-dirty" if dirty.stdout.strip() else "")


class JobRun:
    """The open MLflow run of one job; metrics are buffered and sent in batches."""

    def __init__(self, *, client: MlflowClient, run_id: str, batch_size: int):
        self.client = client
        self.run_id = run_id
        self.batch_size = batch_size
        self._pending: list[Metric] = []

    def log_metrics(self, metrics: Mapping[str, float], *, step: int = 0) -> None:
        """Queue scalar metrics at ``step``; sent with the next full batch or :meth:`flush`."""
        now = int(time.time() * 1000)
        self._pending.extend(Metric(k, float(v), now, int(step)) for k, v in metrics.items())
        if len(self._pending) >= self.batch_size:
            self.flush()

    def log_series(self, name: str, values: Sequence[float], steps: Sequence[int] | None = None) -> None:
        """Queue a whole history (e.g. a training loss per step) under one metric name."""
        now = int(time.time() * 1000)
        steps = range(len(values)) if steps is None else steps
        self._pending.extend(Metric(name, float(v), now, int(s)) for s, v in zip(steps, values, strict=True))
        while len(self._pending) >= self.batch_size:
            self.flush()

    def flush(self) -> None:
        """Send the queued metrics, at most ``batch_size`` per request."""
        while self._pending:
            chunk, self._pending = self._pending[: self.batch_size], self._pending[self.batch_size:]
            retry(self.client.log_batch, self.run_id, metrics=chunk)

    def log_artifact(self, path: str | Path, artifact_path: str | None = None) -> None:
        """Copy a file into the run's artifact directory."""
        retry(self.client.log_artifact, self.run_id, str(path), artifact_path)

    def log_dataset(self, path: str | Path, *, name: str, digest: str, context: str) -> None:
        """Record the file ``path`` as a dataset input of the run (the Dataset column and lineage of the UI).

        Args:
            name: the dataset's name (e.g. "milan").
            digest: its content hash (shown beside the name; a new file gives a new dataset entry).
            context: what the run did with it ("evaluation", "training", ...).
        """
        from mlflow.data.dataset_source_registry import resolve_dataset_source
        from mlflow.data.meta_dataset import MetaDataset
        from mlflow.entities import DatasetInput, InputTag

        with warnings.catch_warnings():  # two registered local-file source types match a file URI; either will do
            warnings.simplefilter("ignore", UserWarning)
            source = resolve_dataset_source(Path(path).resolve().as_uri())
        dataset = MetaDataset(source, name=name, digest=digest)
        entry = DatasetInput(dataset=dataset._to_mlflow_entity(), tags=[InputTag("mlflow.data.context", context)])
        retry(self.client.log_inputs, self.run_id, datasets=[entry])

    def set_tags(self, tags: Mapping[str, Any]) -> None:
        """Add tags to the run (one request)."""
        from mlflow.entities import RunTag

        retry(self.client.log_batch, self.run_id, tags=[RunTag(k, str(v)) for k, v in tags.items()])


def _runs_of(client: MlflowClient, exp_ids: Sequence[str], key: str, status: str, workdir: str) -> list:
    """Active runs of the experiments with job key ``key``, working directory ``workdir`` and the given status."""
    query = f"tags.job_key = '{key}' and tags.workdir = '{workdir}' and attributes.status = '{status}'"
    return retry(client.search_runs, list(exp_ids), filter_string=query, max_results=1000)


class Terminated(Exception):
    """Raised inside a job when Snakemake terminates it, so its run ends FAILED."""


def keep_unlogged(paths: Sequence[str | Path], keep_dir: str | Path) -> list[Path]:
    """Copy the files of ``paths`` that exist into ``keep_dir`` (atomically, each under its own name); returns the
    copies. A job whose tracking failed calls it before it fails, since Snakemake deletes a failed job's outputs."""
    kept = []
    for path in map(Path, paths):
        if not path.is_file():
            continue
        dest = Path(keep_dir) / path.name
        with atomic_path(dest) as tmp:
            shutil.copy2(path, tmp)
        kept.append(dest)
    return kept


@contextlib.contextmanager
def job_run(*, mlflow_cfg: Mapping[str, Any], settings: Mapping[str, Any], stage: str, dataset: str,
            method: str, seed: int, config_hash: str, repo: str | Path = ".",
            keep: Sequence[str | Path] = (), kind: str = "main") -> Iterator[JobRun]:
    """Open the one MLflow run of a job; end it FINISHED, or FAILED if the body raises or is terminated.

    Args:
        mlflow_cfg: the ``mlflow`` section (tracking_uri or store, artifacts, experiment, batch_size, http,
            unlogged).
        settings: the settings slice the job read (plain form), logged as params.
        stage: "train" or "evaluate" (a main run); the figures' runs name their own.
        dataset, method, seed: the job's wildcards.
        config_hash: hash of that slice (tag).
        repo: the repository, for the git commit tag.
        keep: the job's result files. When a tracking call fails for good (:class:`TrackingError`), those
            already written are copied to ``<mlflow.unlogged>/<job key>/`` before the job fails, and the error
            names them: Snakemake deletes a failed job's outputs, the copies stay.
        kind: what the run is (:data:`RUN_KINDS`; the ``kind`` tag): "main" runs go to the experiment
            ``mlflow.experiment``, the others to its figures' experiment (:func:`experiment_of`).

    Yields:
        The :class:`JobRun`.

    Raises:
        TrackingError: a tracking call failed after its retries; the message names the store, the call, the job
            and the kept files. :class:`TrackingAuthError` (a subclass) when the server refused the credentials:
            not retried, the files kept alike.
    """
    client = store_client(mlflow_cfg)
    key = f"{stage}/{dataset}/{method}/seed{seed}"
    try:
        workdir = workdir_tag()
        if not uses_server(mlflow_cfg):  # a store copied with its tree is made this tree's before anything is read
            main = main_experiment(client, mlflow_cfg)
            if main.tags.get(TREE_TAG) != workdir or main.artifact_location != \
                    Path(mlflow_cfg["artifacts"]).resolve().as_uri():
                adopt_store(mlflow_cfg, workdir=workdir)
        # Earlier runs of the job key are looked up in both experiments: a store from before the figures' runs had
        # their own experiment holds them in the main one, and they are replaced as any earlier run.
        exp_id, both = run_experiments(client, mlflow_cfg, kind)
        for stale in _runs_of(client, both, key, "RUNNING", workdir):  # left behind by a killed job
            retry(client.set_terminated, stale.info.run_id, RunStatus.to_string(RunStatus.KILLED))
    except TrackingError as err:
        again = ("with credentials the server accepts" if isinstance(err, TrackingAuthError) else
                 "once the tracking store answers")
        raise type(err)(f"job {key}: {err}; nothing was computed, run the job again {again}") from err
    tags = {"job_key": key, "kind": kind, "stage": stage, "dataset": dataset, "method": method, "seed": str(seed),
            "workdir": workdir, "profile": settings["profile"], "git_commit": git_commit(repo),
            "config_hash": config_hash, "mlflow.runName": f"{stage}:{dataset}/{method}/seed{seed}"}

    # The handlers are in place before the run exists. While the run is created and its id bound, a SIGTERM or
    # SIGINT is only noted, and raised once the job holds the id, inside the `try` below, which ends the run
    # FAILED: no window is left in which a run exists that nothing will close (SIGKILL aside: the next run of the
    # job key, or the next workflow start, closes such a run KILLED; see close_orphans).
    state = {"defer": True, "pending": None}

    def _on_signal(signum, frame):
        if state["defer"]:
            state["pending"] = signum
            return
        if signum == signal.SIGINT:
            raise KeyboardInterrupt
        raise Terminated(f"terminated by signal {signum}")

    main = threading.current_thread() is threading.main_thread()
    previous = {s: signal.signal(s, _on_signal) for s in (signal.SIGTERM, signal.SIGINT)} if main else {}
    job: JobRun | None = None
    try:
        run = retry(client.create_run, exp_id, tags=tags)
        job = JobRun(client=client, run_id=run.info.run_id, batch_size=int(mlflow_cfg["batch_size"]))
        state["defer"] = False
        if main:
            signal.signal(signal.SIGINT, previous.pop(signal.SIGINT))
        if state["pending"] is not None:
            _on_signal(state["pending"], None)
        params = [Param(k, v) for k, v in sorted(flatten(settings).items())]
        for i in range(0, len(params), MAX_PARAMS_PER_BATCH):
            retry(client.log_batch, job.run_id, params=params[i: i + MAX_PARAMS_PER_BATCH])
        yield job
        job.flush()
        retry(client.set_terminated, job.run_id, RunStatus.to_string(RunStatus.FINISHED))
    except BaseException as err:
        if job is not None:
            with contextlib.suppress(Exception):
                job.flush()
            with contextlib.suppress(Exception):  # the store may be the thing that failed
                retry(client.set_terminated, job.run_id, RunStatus.to_string(RunStatus.FAILED))
        if isinstance(err, TrackingError):
            keep_dir = Path(mlflow_cfg.get("unlogged") or "results/unlogged") / key
            kept = keep_unlogged(keep, keep_dir)
            what = (f"its result files are kept in {keep_dir}: {', '.join(p.name for p in kept)}" if kept else
                    "no result file had been written yet")
            raise type(err)(f"job {key}: {err}; the job fails, {what}") from err
        raise
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    for old in _runs_of(client, both, key, "FINISHED", workdir):
        if old.info.run_id != job.run_id:
            retry(client.delete_run, old.info.run_id)
