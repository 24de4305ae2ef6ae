"""MLflow tracking of the workflow's jobs: one SQLite store, one experiment, one run per job.

The store and the experiment are created once by the ``mlflow_init`` rule (:func:`init_store`); every
training or evaluation job then opens exactly one run with :func:`job_run`. A run is tagged with its job key
(stage/dataset/method/seed), the profile, the git commit and the hash of its settings, and carries the settings
slice it read as params. Metrics go out in batches (one SQLite round trip per batch instead of one per value). When a job is
rerun, the previous FINISHED runs of the same job key are deleted once the new one finishes, so the UI never
shows two finished runs of one job; a job that raises (or is terminated) ends its run FAILED. Tables never
read MLflow: the result files are the source of truth.
"""
from __future__ import annotations

import contextlib
import json
import signal
import threading
import subprocess
import time
import warnings
from pathlib import Path
from typing import Any, Iterator, Mapping, Sequence

from mlflow.entities import Metric, Param, RunStatus
from mlflow.tracking import MlflowClient

MAX_PARAMS_PER_BATCH = 100
"""MLflow refuses log_batch requests with more than 100 params."""
MAX_PARAM_CHARS = 6000
"""MLflow's longest param value."""


def tracking_uri(store: str | Path) -> str:
    """SQLAlchemy URI of the SQLite store at ``store`` (made absolute, so jobs agree from any cwd)."""
    return "sqlite:///" + str(Path(store).resolve())


def _retry(fn, *args, attempts: int = 8, **kwargs):
    """Call ``fn``, retrying while SQLite reports a lock held by a concurrent job (two jobs on two cores)."""
    for i in range(attempts):
        try:
            return fn(*args, **kwargs)
        except Exception as err:  # MLflow wraps SQLAlchemy's OperationalError in its own exception types
            if "database is locked" not in str(err) or i == attempts - 1:
                raise
            time.sleep(0.2 * 2**i)
    raise AssertionError("unreachable")


EXPERIMENT_KIND = ("mlflow.experimentKind", "custom_model_development")
"""The experiment tag that makes the MLflow UI open on the training-runs view (without it, MLflow 3 opens on
the GenAI overview, whose traces page this project never fills)."""


def init_store(*, store: str | Path, artifacts: str | Path, experiment: str) -> dict:
    """Create the SQLite store and the experiment (idempotent), tag it :data:`EXPERIMENT_KIND`, and describe them.

    Args:
        store: path of the SQLite file, e.g. results/mlflow.db.
        artifacts: directory under which each run's artifacts are stored.
        experiment: experiment name.

    Returns:
        {"tracking_uri", "experiment", "experiment_id", "artifact_location"}.
    """
    Path(store).parent.mkdir(parents=True, exist_ok=True)
    Path(artifacts).mkdir(parents=True, exist_ok=True)
    client = MlflowClient(tracking_uri=tracking_uri(store))
    found = client.get_experiment_by_name(experiment)
    location = Path(artifacts).resolve().as_uri()
    if found is None:
        exp_id = client.create_experiment(experiment, artifact_location=location)
    elif found.lifecycle_stage == "deleted":
        client.restore_experiment(found.experiment_id)
        exp_id = found.experiment_id
    else:
        exp_id = found.experiment_id
    client.set_experiment_tag(exp_id, *EXPERIMENT_KIND)
    exp = client.get_experiment(exp_id)
    return {"tracking_uri": tracking_uri(store), "experiment": experiment, "experiment_id": exp.experiment_id,
            "artifact_location": exp.artifact_location}


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
            _retry(self.client.log_batch, self.run_id, metrics=chunk)

    def log_artifact(self, path: str | Path, artifact_path: str | None = None) -> None:
        """Copy a file into the run's artifact directory."""
        _retry(self.client.log_artifact, self.run_id, str(path), artifact_path)

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
        _retry(self.client.log_inputs, self.run_id, datasets=[entry])

    def set_tags(self, tags: Mapping[str, Any]) -> None:
        """Add tags to the run."""
        for k, v in tags.items():
            _retry(self.client.set_tag, self.run_id, k, str(v))


def _runs_of(client: MlflowClient, exp_id: str, key: str, status: str) -> list:
    """Active runs of the experiment with job key ``key`` and the given status."""
    query = f"tags.job_key = '{key}' and attributes.status = '{status}'"
    return _retry(client.search_runs, [exp_id], filter_string=query, max_results=1000)


class _Terminated(Exception):
    """Raised inside a job when Snakemake terminates it, so its run ends FAILED."""


@contextlib.contextmanager
def job_run(*, mlflow_cfg: Mapping[str, Any], settings: Mapping[str, Any], stage: str, dataset: str,
            method: str, seed: int, config_hash: str, repo: str | Path = ".") -> Iterator[JobRun]:
    """Open the one MLflow run of a job; end it FINISHED, or FAILED if the body raises or is terminated.

    Args:
        mlflow_cfg: the ``mlflow`` section (store, artifacts, experiment, batch_size).
        settings: the settings slice the job read (plain form), logged as params.
        stage: "train" or "evaluate".
        dataset, method, seed: the job's wildcards.
        config_hash: hash of that slice (tag).
        repo: the repository, for the git commit tag.

    Yields:
        The :class:`JobRun`.
    """
    store = Path(mlflow_cfg["store"])
    if not store.exists():
        raise FileNotFoundError(f"{store}: MLflow store missing; it is created by the mlflow_init rule "
                                f"(run `snakemake --cores 1 --forcerun mlflow_init mlflow_init`)")
    client = MlflowClient(tracking_uri=tracking_uri(store))
    exp = _retry(client.get_experiment_by_name, mlflow_cfg["experiment"])
    if exp is None:
        raise LookupError(f"{store}: experiment {mlflow_cfg['experiment']!r} missing; the mlflow_init rule creates it")
    key = f"{stage}/{dataset}/{method}/seed{seed}"
    for stale in _runs_of(client, exp.experiment_id, key, "RUNNING"):  # left behind by a killed job
        _retry(client.set_terminated, stale.info.run_id, RunStatus.to_string(RunStatus.KILLED))
    tags = {"job_key": key, "stage": stage, "dataset": dataset, "method": method, "seed": str(seed),
            "profile": settings["profile"], "git_commit": git_commit(repo), "config_hash": config_hash,
            "mlflow.runName": f"{stage}:{dataset}/{method}/seed{seed}"}

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
        raise _Terminated(f"terminated by signal {signum}")

    main = threading.current_thread() is threading.main_thread()
    previous = {s: signal.signal(s, _on_signal) for s in (signal.SIGTERM, signal.SIGINT)} if main else {}
    job: JobRun | None = None
    try:
        run = _retry(client.create_run, exp.experiment_id, tags=tags)
        job = JobRun(client=client, run_id=run.info.run_id, batch_size=int(mlflow_cfg["batch_size"]))
        state["defer"] = False
        if main:
            signal.signal(signal.SIGINT, previous.pop(signal.SIGINT))
        if state["pending"] is not None:
            _on_signal(state["pending"], None)
        params = [Param(k, v) for k, v in sorted(flatten(settings).items())]
        for i in range(0, len(params), MAX_PARAMS_PER_BATCH):
            _retry(client.log_batch, job.run_id, params=params[i: i + MAX_PARAMS_PER_BATCH])
        yield job
        job.flush()
    except BaseException:
        if job is not None:
            with contextlib.suppress(Exception):
                job.flush()
            _retry(client.set_terminated, job.run_id, RunStatus.to_string(RunStatus.FAILED))
        raise
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    _retry(client.set_terminated, job.run_id, RunStatus.to_string(RunStatus.FINISHED))
    for old in _runs_of(client, exp.experiment_id, key, "FINISHED"):
        if old.info.run_id != job.run_id:
            _retry(client.delete_run, old.info.run_id)



def close_orphans(*, store: str | Path, experiment: str) -> int:
    """End every run of the experiment still marked RUNNING as KILLED; returns how many.

    Called when a workflow starts (Snakefile `onstart`): Snakemake's lock guarantees no job of this working
    directory runs then, so a RUNNING run can only be one whose job was killed with SIGKILL (or lost its machine).
    Nothing happens when the store does not exist yet.
    """
    if not Path(store).exists():
        return 0
    client = MlflowClient(tracking_uri=tracking_uri(store))
    exp = _retry(client.get_experiment_by_name, experiment)
    if exp is None:
        return 0
    query = "attributes.status = 'RUNNING'"
    runs = _retry(client.search_runs, [exp.experiment_id], filter_string=query, max_results=10000)
    for run in runs:
        _retry(client.set_terminated, run.info.run_id, RunStatus.to_string(RunStatus.KILLED))
    return len(runs)


def attach_figures(*, mlflow_cfg: Mapping[str, Any], paths: Sequence[str | Path], stage: str | Sequence[str],
                   datasets: Sequence[str] | None = None, methods: Sequence[str] | None = None,
                   profile: str | None = None, artifact_path: str = "figures") -> int:
    """Log the figure files ``paths`` as artifacts (under ``artifact_path``) of every FINISHED run they concern:
    the runs of ``stage`` (one or several), restricted to ``datasets``, ``methods`` and ``profile`` where given.

    A figure is drawn after the runs it shows have ended; MLflow keeps a run's artifact store open after that, so
    the figure lands beside the run's result files. Returns how many runs received the files.
    """
    store = mlflow_cfg["store"]
    client = MlflowClient(tracking_uri=tracking_uri(store))
    exp = _retry(client.get_experiment_by_name, mlflow_cfg["experiment"])
    if exp is None:
        raise LookupError(f"{store}: experiment {mlflow_cfg['experiment']!r} missing; the mlflow_init rule creates it")
    stages = [stage] if isinstance(stage, str) else list(stage)
    query = "attributes.status = 'FINISHED'"  # tags allow no IN; the stages are chosen below
    if profile is not None:
        query += f" and tags.profile = '{profile}'"
    runs = _retry(client.search_runs, [exp.experiment_id], filter_string=query, max_results=50000)
    chosen = [r for r in runs if r.data.tags.get("stage") in stages
              and (datasets is None or r.data.tags.get("dataset") in datasets)
              and (methods is None or r.data.tags.get("method") in methods)]
    for r in chosen:
        for p in paths:
            _retry(client.log_artifact, r.info.run_id, str(p), artifact_path)
    return len(chosen)


def attach_figure_outputs(attach: str, out: Mapping[str, str | Path]) -> int:
    """A figure rule's side of ``figure_attach`` (workflow/rules/common.smk): log the PNG and PDF of ``out`` beside
    the runs ``attach`` (its canonical JSON) names; returns how many runs received them."""
    sel = json.loads(attach)
    return attach_figures(mlflow_cfg=sel["mlflow"], paths=[out["png"], out["pdf"]], stage=sel["stages"],
                          datasets=sel["datasets"], methods=sel["methods"], profile=sel["profile"])
