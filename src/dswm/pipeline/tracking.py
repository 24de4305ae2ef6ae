"""MLflow tracking of the workflow's jobs: one store, one experiment, one run per job.

The store is the SQLite file ``mlflow.store`` on one machine, or, where ``mlflow.tracking_uri`` names one, an MLflow
tracking server (on a cluster: PostgreSQL behind it, artifacts on the shared filesystem; docs/CLUSTER.md). The
store and the experiment are created once by the ``mlflow_init`` rule (:func:`init_store`); every training or
evaluation job then opens exactly one run with :func:`job_run`. A run is tagged with its job key
(stage/dataset/method/seed), the working directory it ran in, the profile, the git commit and the hash of its
settings, and carries the settings slice it read as params. Metrics go out in batches (one round trip per batch
instead of one per value). When a job is rerun, the previous FINISHED runs of the same job key and working
directory are deleted once the new one finishes, so the UI never shows two finished runs of one job; a job that
raises (or is terminated) ends its run FAILED. A server's HTTP errors (refused connections, 408, 429, 5xx) are
retried with exponential backoff a bounded number of times (``mlflow.http``); a call that still fails raises
:class:`TrackingError`, naming the server and the call, and the job's result files are kept (``mlflow.unlogged``)
before the job fails. Tables never read MLflow: the result files are the source of truth.
"""
from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import threading
import subprocess
import time
import warnings
from pathlib import Path
from typing import Any, Iterator, Mapping, Sequence

from mlflow.entities import Metric, Param, RunStatus
from mlflow.tracking import MlflowClient

from prep.atomic import atomic_path

MAX_PARAMS_PER_BATCH = 100
"""MLflow refuses log_batch requests with more than 100 params."""
MAX_PARAM_CHARS = 6000
"""MLflow's longest param value."""

HTTP_ENV = {"max_retries": "MLFLOW_HTTP_REQUEST_MAX_RETRIES", "backoff_factor": "MLFLOW_HTTP_REQUEST_BACKOFF_FACTOR",
            "timeout_s": "MLFLOW_HTTP_REQUEST_TIMEOUT"}
"""``mlflow.http`` key -> the environment variable through which MLflow's REST client reads it. The client retries
refused connections and the responses 408, 429, 500, 502, 503 and 504 with waits of backoff_factor x 1, 2, 4, ...
seconds (each at most 120 s), at most max_retries times, each request waiting at most timeout_s."""


class TrackingError(RuntimeError):
    """An MLflow call failed for good (after the bounded retries); the message names the store and the call."""


def sqlite_uri(store: str | Path) -> str:
    """SQLAlchemy URI of the SQLite store at ``store`` (made absolute, so jobs agree from any cwd)."""
    return "sqlite:///" + str(Path(store).resolve())


def tracking_uri(mlflow_cfg: Mapping[str, Any]) -> str:
    """Where the runs of ``mlflow_cfg`` (the ``mlflow`` section) are logged: its ``tracking_uri`` (a tracking server)
    when set, else the SQLite store ``store``."""
    return mlflow_cfg.get("tracking_uri") or sqlite_uri(mlflow_cfg["store"])


def uses_server(mlflow_cfg: Mapping[str, Any]) -> bool:
    """True when ``mlflow_cfg`` names a tracking server instead of the SQLite store."""
    return bool(mlflow_cfg.get("tracking_uri"))


def configure_http(http: Mapping[str, Any] | None) -> None:
    """Set MLflow's HTTP retry, backoff and timeout for this process from ``mlflow.http`` (:data:`HTTP_ENV`)."""
    for key, var in HTTP_ENV.items():
        if http and http.get(key) is not None:
            os.environ[var] = str(int(http[key]))


def client_for(mlflow_cfg: Mapping[str, Any]) -> MlflowClient:
    """The MLflow client of ``mlflow_cfg``, with its HTTP retries configured (:func:`configure_http`)."""
    configure_http(mlflow_cfg.get("http"))
    return MlflowClient(tracking_uri=tracking_uri(mlflow_cfg))


def _describe(fn) -> tuple[str, str]:
    """(store, call) of an MLflow client method, for error messages."""
    owner = getattr(fn, "__self__", None)
    uri = getattr(owner, "_tracking_client", None)
    uri = getattr(uri, "tracking_uri", None) or "the MLflow store"
    return str(uri), getattr(fn, "__name__", "call")


def _retry(fn, *args, attempts: int = 8, **kwargs):
    """Call ``fn``, retrying while SQLite reports a lock held by a concurrent job (two jobs on two cores).

    A tracking server's transient HTTP errors are retried by MLflow's client itself (:data:`HTTP_ENV`). Any other
    failure, or one that outlasts the retries, raises :class:`TrackingError` naming the store and the call.
    """
    for i in range(attempts):
        try:
            return fn(*args, **kwargs)
        except TrackingError:
            raise
        except Exception as err:  # MLflow wraps SQLAlchemy's OperationalError in its own exception types
            if "database is locked" in str(err) and i < attempts - 1:
                time.sleep(0.2 * 2**i)
                continue
            uri, call = _describe(fn)
            raise TrackingError(f"MLflow at {uri}: {call} failed: {type(err).__name__}: {err}") from err
    raise AssertionError("unreachable")


EXPERIMENT_KIND = ("mlflow.experimentKind", "custom_model_development")
"""The experiment tag that makes the MLflow UI open on the training-runs view (without it, MLflow 3 opens on
the GenAI overview, whose traces page this project never fills)."""


def init_store(*, store: str | Path, artifacts: str | Path, experiment: str, tracking_uri: str | None = None,
               http: Mapping[str, Any] | None = None) -> dict:
    """Create the store (the SQLite file, unless ``tracking_uri`` names a server) and the experiment (idempotent),
    tag it :data:`EXPERIMENT_KIND`, and describe them.

    Args:
        store: path of the SQLite file, e.g. results/mlflow.db (unused when ``tracking_uri`` is given).
        artifacts: directory under which each run's artifacts are stored; with a server, a directory on the
            filesystem every job shares: the experiment's artifact location, written by the jobs directly.
        experiment: experiment name.
        tracking_uri: the tracking server's URL (``mlflow.tracking_uri``), or None for the SQLite store.
        http: ``mlflow.http`` (retries, backoff and timeout of a server's requests).

    Returns:
        {"tracking_uri", "experiment", "experiment_id", "artifact_location"}.

    Raises:
        TrackingError: the server cannot be reached (after the retries), named with the call that failed.
    """
    cfg = {"store": str(store), "tracking_uri": tracking_uri, "http": http}
    if not uses_server(cfg):
        Path(store).parent.mkdir(parents=True, exist_ok=True)
    Path(artifacts).mkdir(parents=True, exist_ok=True)
    client = client_for(cfg)
    found = _retry(client.get_experiment_by_name, experiment)
    location = Path(artifacts).resolve().as_uri()
    if found is None:
        try:
            exp_id = _retry(client.create_experiment, experiment, artifact_location=location)
        except TrackingError:  # another workflow on the same server created it first
            found = _retry(client.get_experiment_by_name, experiment)
            if found is None:
                raise
            exp_id = found.experiment_id
    elif found.lifecycle_stage == "deleted":
        _retry(client.restore_experiment, found.experiment_id)
        exp_id = found.experiment_id
    else:
        exp_id = found.experiment_id
    _retry(client.set_experiment_tag, exp_id, *EXPERIMENT_KIND)
    exp = _retry(client.get_experiment, exp_id)
    return {"tracking_uri": tracking_uri or sqlite_uri(store), "experiment": experiment,
            "experiment_id": exp.experiment_id, "artifact_location": exp.artifact_location}


def ensure_store(mlflow_cfg: Mapping[str, Any]) -> dict:
    """:func:`init_store` for the ``mlflow`` section ``mlflow_cfg``: its store (or server), artifact location and
    experiment exist afterwards, created where missing. Run by the ``mlflow_init`` job, and as a workflow starts
    (workflow/rules/mlflow.smk ``onstart``) for a store or server that changed since ``mlflow_init`` ran."""
    return init_store(store=mlflow_cfg["store"], artifacts=mlflow_cfg["artifacts"],
                      experiment=mlflow_cfg["experiment"], tracking_uri=mlflow_cfg.get("tracking_uri"),
                      http=mlflow_cfg.get("http"))


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
        """Add tags to the run (one request)."""
        from mlflow.entities import RunTag

        _retry(self.client.log_batch, self.run_id, tags=[RunTag(k, str(v)) for k, v in tags.items()])


def workdir_tag() -> str:
    """The ``workdir`` tag of a run: the working directory its job ran in (the workflow's root, absolute).

    Snakemake's lock keeps two workflows out of one working directory, so a job key is unique within it; on a
    tracking server that several workflows share, the tag keeps each workflow's reruns and orphans its own."""
    return str(Path.cwd().resolve())


def _runs_of(client: MlflowClient, exp_id: str, key: str, status: str, workdir: str) -> list:
    """Active runs of the experiment with job key ``key``, working directory ``workdir`` and the given status."""
    query = f"tags.job_key = '{key}' and tags.workdir = '{workdir}' and attributes.status = '{status}'"
    return _retry(client.search_runs, [exp_id], filter_string=query, max_results=1000)


class _Terminated(Exception):
    """Raised inside a job when Snakemake terminates it, so its run ends FAILED."""


def _store_client(mlflow_cfg: Mapping[str, Any]) -> MlflowClient:
    """:func:`client_for`, once the SQLite store is known to exist (a client would create an empty one)."""
    if not uses_server(mlflow_cfg) and not Path(mlflow_cfg["store"]).exists():
        raise FileNotFoundError(f"{mlflow_cfg['store']}: MLflow store missing; it is created by the mlflow_init rule "
                                f"(run `snakemake --cores 1 --forcerun mlflow_init mlflow_init`)")
    return client_for(mlflow_cfg)


def _experiment(client: MlflowClient, mlflow_cfg: Mapping[str, Any]):
    """The configured experiment, checked to exist (the mlflow_init rule creates it)."""
    exp = _retry(client.get_experiment_by_name, mlflow_cfg["experiment"])
    if exp is None:
        raise LookupError(f"{tracking_uri(mlflow_cfg)}: experiment {mlflow_cfg['experiment']!r} missing; the "
                          f"mlflow_init rule creates it")
    return exp


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
            keep: Sequence[str | Path] = ()) -> Iterator[JobRun]:
    """Open the one MLflow run of a job; end it FINISHED, or FAILED if the body raises or is terminated.

    Args:
        mlflow_cfg: the ``mlflow`` section (tracking_uri or store, artifacts, experiment, batch_size, http,
            unlogged).
        settings: the settings slice the job read (plain form), logged as params.
        stage: "train" or "evaluate".
        dataset, method, seed: the job's wildcards.
        config_hash: hash of that slice (tag).
        repo: the repository, for the git commit tag.
        keep: the job's result files. When a tracking call fails for good (:class:`TrackingError`), those
            already written are copied to ``<mlflow.unlogged>/<job key>/`` before the job fails, and the error
            names them: Snakemake deletes a failed job's outputs, the copies stay.

    Yields:
        The :class:`JobRun`.

    Raises:
        TrackingError: a tracking call failed after its retries; the message names the store, the call, the job
            and the kept files.
    """
    client = _store_client(mlflow_cfg)
    key = f"{stage}/{dataset}/{method}/seed{seed}"
    try:
        exp = _experiment(client, mlflow_cfg)
        workdir = workdir_tag()
        for stale in _runs_of(client, exp.experiment_id, key, "RUNNING", workdir):  # left behind by a killed job
            _retry(client.set_terminated, stale.info.run_id, RunStatus.to_string(RunStatus.KILLED))
    except TrackingError as err:
        raise TrackingError(f"job {key}: {err}; nothing was computed, run the job again once the tracking store "
                            f"answers") from err
    tags = {"job_key": key, "stage": stage, "dataset": dataset, "method": method, "seed": str(seed),
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
        _retry(client.set_terminated, job.run_id, RunStatus.to_string(RunStatus.FINISHED))
    except BaseException as err:
        if job is not None:
            with contextlib.suppress(Exception):
                job.flush()
            with contextlib.suppress(Exception):  # the store may be the thing that failed
                _retry(client.set_terminated, job.run_id, RunStatus.to_string(RunStatus.FAILED))
        if isinstance(err, TrackingError):
            keep_dir = Path(mlflow_cfg.get("unlogged") or "results/unlogged") / key
            kept = keep_unlogged(keep, keep_dir)
            what = (f"its result files are kept in {keep_dir}: {', '.join(p.name for p in kept)}" if kept else
                    "no result file had been written yet")
            raise TrackingError(f"job {key}: {err}; the job fails, {what}") from err
        raise
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    for old in _runs_of(client, exp.experiment_id, key, "FINISHED", workdir):
        if old.info.run_id != job.run_id:
            _retry(client.delete_run, old.info.run_id)


def close_orphans(*, mlflow_cfg: Mapping[str, Any], workdir: str | None = None) -> int:
    """End every run of this working directory (``workdir``, default :func:`workdir_tag`) still marked RUNNING as
    KILLED; returns how many.

    Called when a workflow starts (Snakefile `onstart`): Snakemake's lock guarantees no job of this working
    directory runs then, so such a run can only be one whose job was killed with SIGKILL (or lost its machine).
    Runs of other working directories on a shared tracking server are left alone. Nothing happens when the SQLite
    store does not exist yet.
    """
    if not uses_server(mlflow_cfg) and not Path(mlflow_cfg["store"]).exists():
        return 0
    client = client_for(mlflow_cfg)
    exp = _retry(client.get_experiment_by_name, mlflow_cfg["experiment"])
    if exp is None:
        return 0
    query = f"attributes.status = 'RUNNING' and tags.workdir = '{workdir or workdir_tag()}'"
    runs = _retry(client.search_runs, [exp.experiment_id], filter_string=query, max_results=10000)
    for run in runs:
        _retry(client.set_terminated, run.info.run_id, RunStatus.to_string(RunStatus.KILLED))
    return len(runs)


def attach_figures(*, mlflow_cfg: Mapping[str, Any], paths: Sequence[str | Path], stage: str | Sequence[str],
                   datasets: Sequence[str] | None = None, methods: Sequence[str] | None = None,
                   profile: str | None = None, artifact_path: str = "figures") -> int:
    """Log the figure files ``paths`` as artifacts (under ``artifact_path``) of every FINISHED run of this working
    directory they concern: the runs of ``stage`` (one or several), restricted to ``datasets``, ``methods`` and
    ``profile`` where given.

    A figure is drawn after the runs it shows have ended; MLflow keeps a run's artifact store open after that, so
    the figure lands beside the run's result files. Returns how many runs received the files.
    """
    client = _store_client(mlflow_cfg)
    exp = _experiment(client, mlflow_cfg)
    stages = [stage] if isinstance(stage, str) else list(stage)
    # tags allow no IN; the stages are chosen below
    query = f"attributes.status = 'FINISHED' and tags.workdir = '{workdir_tag()}'"
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


def attach_figure_outputs(attach: Mapping[str, Any], out: Mapping[str, str | Path]) -> int:
    """A figure rule's side of ``figure_attach`` (workflow/rules/common.smk): log the PNG and PDF of ``out`` beside
    the runs ``attach`` (the value of that Untracked param) names; returns how many runs received them."""
    sel = attach
    return attach_figures(mlflow_cfg=sel["mlflow"], paths=[out["png"], out["pdf"]], stage=sel["stages"],
                          datasets=sel["datasets"], methods=sel["methods"], profile=sel["profile"])
