"""MLflow tracking of the workflow's jobs: one store, two experiments, one run per job.

The store is the SQLite file ``mlflow.store`` on one machine, or, where ``mlflow.tracking_uri`` names one, an MLflow
tracking server (on a cluster: PostgreSQL behind it, artifacts on the shared filesystem; docs/CLUSTER.md). The
store and its experiments are created once by the ``mlflow_init`` rule (:func:`init_store`): ``mlflow.experiment``
holds the tables' train and evaluate runs, ``<experiment>-figures`` the runs behind the figures only (extra runs,
probe, world-model quality), so the UI opens on the tables' runs. Every such job then opens exactly one run with
:func:`job_run`. A SQLite store inside the tree belongs to that tree: after the tree is copied or moved, the store's
absolute paths are made the copy's own (:func:`adopt_store`), so a job in the copy never writes into the tree it was
copied from. A run is tagged with its kind (:data:`RUN_KINDS`), its job key (stage/dataset/method/seed), the
working directory it ran in, the profile, the git commit and the hash of its
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
import sqlite3
import threading
import subprocess
import time
import warnings
from pathlib import Path
from typing import Any, Iterator, Mapping, Sequence
from urllib.parse import unquote, urlparse

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

RUN_KINDS = {
    "main": "a train or evaluate job of the tables (the workflow's `tables` target)",
    "extra": "an extra run behind a figure (do(s) probe, scaling sweeps; workflow/rules/extra.smk)",
    "probe": "the sample-efficiency probe of a train job's snapshots (workflow/rules/probes.smk)",
    "wm_quality": "the world-model quality replay of a DSWM model (workflow/rules/wm.smk)",
}
"""The ``kind`` tag of a run -> what the run is. The main runs go to the experiment ``mlflow.experiment``; the
others, which only the figures use, to :func:`figures_experiment`, so the UI opens on the tables' runs alone."""
FIGURES_SUFFIX = "-figures"
"""The figures' experiment is named after the main one with this suffix (``dswm`` -> ``dswm-figures``)."""
EXPERIMENT_NOTES = {
    "main": "The runs of the tables: one train or evaluate run per job (tag kind = main). The runs behind the "
            "figures only are in the experiment '{figures}'.",
    "figures": "The runs behind the figures only, none a table's source: extra runs, the sample-efficiency probe "
               "and the world-model quality replay (tag kind = extra, probe or wm_quality). The tables' runs are "
               "in the experiment '{main}'.",
}
"""Each experiment's description (the ``mlflow.note.content`` tag the UI shows above its runs)."""


def figures_experiment(experiment: str) -> str:
    """The name of the experiment of the figures' runs, beside the main ``experiment``."""
    return experiment + FIGURES_SUFFIX


def experiment_of(mlflow_cfg: Mapping[str, Any], kind: str) -> str:
    """The experiment a run of ``kind`` (a key of :data:`RUN_KINDS`) is logged to."""
    if kind not in RUN_KINDS:
        raise ValueError(f"run kind {kind!r}: expected one of {', '.join(RUN_KINDS)}")
    main = mlflow_cfg["experiment"]
    return main if kind == "main" else figures_experiment(main)


def _ensure_experiment(client: MlflowClient, experiment: str, part: str, location: str) -> str:
    """The id of the active experiment ``part`` ("main" or "figures") of the main ``experiment``, created (artifacts
    under ``location``) or restored if needed, tagged :data:`EXPERIMENT_KIND` and described
    (:data:`EXPERIMENT_NOTES`)."""
    names = {"main": experiment, "figures": figures_experiment(experiment)}
    found = _retry(client.get_experiment_by_name, names[part])
    if found is None:
        try:
            exp_id = _retry(client.create_experiment, names[part], artifact_location=location)
        except TrackingError:  # another workflow (or job) on the same store created it first
            found = _retry(client.get_experiment_by_name, names[part])
            if found is None:
                raise
    if found is not None:
        exp_id = found.experiment_id
        if found.lifecycle_stage == "deleted":
            _retry(client.restore_experiment, exp_id)
    _retry(client.set_experiment_tag, exp_id, *EXPERIMENT_KIND)
    _retry(client.set_experiment_tag, exp_id, "mlflow.note.content", EXPERIMENT_NOTES[part].format(**names))
    return exp_id


def init_store(*, store: str | Path, artifacts: str | Path, experiment: str, tracking_uri: str | None = None,
               http: Mapping[str, Any] | None = None) -> dict:
    """Create the store (the SQLite file, unless ``tracking_uri`` names a server) and its two experiments
    (idempotent): ``experiment``, of the tables' runs, and :func:`figures_experiment`, of the runs behind the figures
    only; tag both :data:`EXPERIMENT_KIND` and describe each (:data:`EXPERIMENT_NOTES`); describe them.

    Args:
        store: path of the SQLite file, e.g. results/mlflow.db (unused when ``tracking_uri`` is given).
        artifacts: directory under which each run's artifacts are stored; with a server, a directory on the
            filesystem every job shares: the experiments' artifact location, written by the jobs directly.
        experiment: name of the main experiment.
        tracking_uri: the tracking server's URL (``mlflow.tracking_uri``), or None for the SQLite store.
        http: ``mlflow.http`` (retries, backoff and timeout of a server's requests).

    Returns:
        {"tracking_uri", "experiment", "experiment_id", "artifact_location", "figures_experiment",
        "figures_experiment_id"}.

    Raises:
        TrackingError: the server cannot be reached (after the retries), named with the call that failed.
    """
    cfg = {"store": str(store), "tracking_uri": tracking_uri, "http": http}
    if not uses_server(cfg):
        Path(store).parent.mkdir(parents=True, exist_ok=True)
    Path(artifacts).mkdir(parents=True, exist_ok=True)
    client = client_for(cfg)
    location = Path(artifacts).resolve().as_uri()
    ids = {part: _ensure_experiment(client, experiment, part, location) for part in EXPERIMENT_NOTES}
    adopt_store({**cfg, "artifacts": str(artifacts), "experiment": experiment})  # a SQLite store copied with its tree
    exp = _retry(client.get_experiment, ids["main"])
    return {"tracking_uri": tracking_uri or sqlite_uri(store), "experiment": experiment,
            "experiment_id": exp.experiment_id, "artifact_location": exp.artifact_location,
            "figures_experiment": figures_experiment(experiment), "figures_experiment_id": ids["figures"]}


TREE_TAG = "dswm.tree"
"""Experiment tag of a SQLite store: the working directory (tree) whose store it is (:func:`adopt_store`)."""


def _tree_root(location: str, artifacts: str | Path) -> str | None:
    """The tree an artifact location ``file://<root>/<artifacts>`` lies in, for a relative ``artifacts``."""
    rel = Path(artifacts)
    if rel.is_absolute() or not location.startswith("file://"):
        return None
    path = Path(unquote(urlparse(location).path))
    n = len(rel.parts)
    return str(Path(*path.parts[:-n])) if n and path.parts[-n:] == rel.parts else None


def _moved(text: str, old_root: str, new_root: str) -> str:
    """``text`` with the file URI of ``old_root`` (and what lies under it) made that of ``new_root``."""
    old, new = Path(old_root).as_uri(), Path(new_root).as_uri()
    return new + text[len(old):] if text == old or text.startswith(old + "/") else text.replace(old + "/", new + "/")


def adopt_store(mlflow_cfg: Mapping[str, Any], *, workdir: str | None = None) -> dict | None:
    """Make the SQLite store of this tree this tree's own, after the tree was copied or moved (``cp -a``, ``mv``).

    MLflow keeps absolute paths in the store: the experiment's artifact location (where every new run's artifacts
    go), each run's artifact URI, the ``workdir`` tag of each run and the file URIs of its dataset inputs. In a copy
    they still name the tree it was copied from, so without this a job in the copy would write its artifacts into
    the original tree, and a rerun there would not replace the finished run it inherited. MLflow has no call that
    changes an artifact location, so the store is updated in one SQLite transaction (``BEGIN IMMEDIATE``: a
    concurrent job waits): the experiment's artifact location becomes this tree's ``mlflow.artifacts``, and every
    path of the tree the store came from (its :data:`TREE_TAG`, or for a store without that tag the tree its
    artifact location lies in) becomes the same path under this tree: the runs' artifacts (copied with the tree)
    are then read from here, and a rerun here replaces the run the copy inherited (:func:`job_run`). The original
    tree's store and files are never touched.

    Only a SQLite store that lies inside ``workdir`` is adopted: with a tracking server (``mlflow.tracking_uri``)
    artifacts go where the server says, and a store outside the tree may be shared with other trees. Called when a
    workflow starts (Snakefile ``onstart``), by :func:`init_store` and by a job whose experiment still names
    another tree; it does nothing when the store is already this tree's.

    Args:
        mlflow_cfg: the ``mlflow`` section (store, artifacts, experiment, tracking_uri).
        workdir: the tree (default :func:`workdir_tag`, the working directory).

    Returns:
        None when nothing changed, else {"from": the tree it came from (or None), "runs": runs moved,
        "artifact_location": [old, new]}.
    """
    if uses_server(mlflow_cfg):
        return None
    root = str(Path(workdir or workdir_tag()).resolve())
    store = Path(mlflow_cfg["store"]).resolve()
    if not store.is_file() or not store.is_relative_to(root):
        return None
    location = Path(mlflow_cfg["artifacts"]).resolve().as_uri()
    with contextlib.closing(sqlite3.connect(store, timeout=60, isolation_level=None)) as db:
        db.execute("BEGIN IMMEDIATE")
        try:
            row = db.execute("SELECT experiment_id, artifact_location FROM experiments WHERE name = ?",
                             (mlflow_cfg["experiment"],)).fetchone()
            if row is None:
                db.execute("ROLLBACK")
                return None
            exp_id, old_location = row
            tag = db.execute("SELECT value FROM experiment_tags WHERE experiment_id = ? AND key = ?",
                             (exp_id, TREE_TAG)).fetchone()
            old_root = tag[0] if tag else _tree_root(old_location or "", mlflow_cfg["artifacts"])
            if tag is not None and old_root == root and old_location == location:
                db.execute("ROLLBACK")
                return None
            # Every experiment of this workflow in the store (the tables' one and the figures' one) moves alike.
            names = (mlflow_cfg["experiment"], figures_experiment(mlflow_cfg["experiment"]))
            ids = [r[0] for r in db.execute("SELECT experiment_id FROM experiments WHERE name IN (?, ?)", names)]
            moved = 0
            for eid in ids:
                if old_root is not None and old_root != root:
                    runs = db.execute("SELECT run_uuid, artifact_uri FROM runs WHERE experiment_id = ?",
                                      (eid,)).fetchall()
                    new_uris = [(_moved(uri, old_root, root), run) for run, uri in runs if uri]
                    db.executemany("UPDATE runs SET artifact_uri = ? WHERE run_uuid = ?", new_uris)
                    moved += db.execute("UPDATE tags SET value = ? WHERE key = 'workdir' AND value = ? AND run_uuid "
                                        "IN (SELECT run_uuid FROM runs WHERE experiment_id = ?)",
                                        (root, old_root, eid)).rowcount
                    sources = db.execute("SELECT dataset_uuid, dataset_source FROM datasets WHERE experiment_id = ?",
                                         (eid,)).fetchall()
                    db.executemany("UPDATE datasets SET dataset_source = ? WHERE dataset_uuid = ?",
                                   [(_moved(src, old_root, root), uid) for uid, src in sources])
                db.execute("UPDATE experiments SET artifact_location = ? WHERE experiment_id = ?", (location, eid))
                db.execute("INSERT OR REPLACE INTO experiment_tags (key, value, experiment_id) VALUES (?, ?, ?)",
                           (TREE_TAG, root, eid))
            db.execute("COMMIT")
        except BaseException:
            db.execute("ROLLBACK")
            raise
    if old_root in (None, root) and old_location == location:
        return None  # only the tag was added: a store of this tree made before the tag existed
    return {"from": old_root if old_root != root else None, "runs": moved,
            "artifact_location": [old_location, location]}


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


def _runs_of(client: MlflowClient, exp_ids: Sequence[str], key: str, status: str, workdir: str) -> list:
    """Active runs of the experiments with job key ``key``, working directory ``workdir`` and the given status."""
    query = f"tags.job_key = '{key}' and tags.workdir = '{workdir}' and attributes.status = '{status}'"
    return _retry(client.search_runs, list(exp_ids), filter_string=query, max_results=1000)


class _Terminated(Exception):
    """Raised inside a job when Snakemake terminates it, so its run ends FAILED."""


def _store_client(mlflow_cfg: Mapping[str, Any]) -> MlflowClient:
    """:func:`client_for`, once the SQLite store is known to exist (a client would create an empty one)."""
    if not uses_server(mlflow_cfg) and not Path(mlflow_cfg["store"]).exists():
        raise FileNotFoundError(f"{mlflow_cfg['store']}: MLflow store missing; it is created by the mlflow_init rule "
                                f"(run `snakemake --cores 1 --forcerun mlflow_init mlflow_init`)")
    return client_for(mlflow_cfg)


def _experiment(client: MlflowClient, mlflow_cfg: Mapping[str, Any]):
    """The configured (main) experiment, checked to exist (the mlflow_init rule creates it)."""
    exp = _retry(client.get_experiment_by_name, mlflow_cfg["experiment"])
    if exp is None:
        raise LookupError(f"{tracking_uri(mlflow_cfg)}: experiment {mlflow_cfg['experiment']!r} missing; the "
                          f"mlflow_init rule creates it")
    return exp


def _experiments(client: MlflowClient, mlflow_cfg: Mapping[str, Any], kind: str) -> tuple[str, list[str]]:
    """(the id of the experiment a run of ``kind`` goes to, the ids of both experiments that exist).

    The main experiment must exist (the mlflow_init rule creates it); the figures' experiment, which mlflow_init
    creates too, is created here when a store made before it lacks it (same artifact location as the main one)."""
    target = experiment_of(mlflow_cfg, kind)
    main = _experiment(client, mlflow_cfg)
    figures = _retry(client.get_experiment_by_name, figures_experiment(main.name))
    if target != main.name and (figures is None or figures.lifecycle_stage == "deleted"):
        fid = _ensure_experiment(client, main.name, "figures", main.artifact_location)
    else:
        fid = figures.experiment_id if figures is not None else None
    return (main.experiment_id if target == main.name else fid), [i for i in (main.experiment_id, fid) if i]


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
            and the kept files.
    """
    client = _store_client(mlflow_cfg)
    key = f"{stage}/{dataset}/{method}/seed{seed}"
    try:
        # Earlier runs of the job key are looked up in both experiments: a store from before the figures' runs had
        # their own experiment holds them in the main one, and they are replaced as any earlier run.
        exp_id, both = _experiments(client, mlflow_cfg, kind)
        workdir = workdir_tag()
        if not uses_server(mlflow_cfg):
            main = _experiment(client, mlflow_cfg)
            if main.tags.get(TREE_TAG) != workdir or main.artifact_location != \
                    Path(mlflow_cfg["artifacts"]).resolve().as_uri():
                if adopt_store(mlflow_cfg, workdir=workdir) is not None:  # a store copied with its tree
                    exp_id, both = _experiments(client, mlflow_cfg, kind)
        for stale in _runs_of(client, both, key, "RUNNING", workdir):  # left behind by a killed job
            _retry(client.set_terminated, stale.info.run_id, RunStatus.to_string(RunStatus.KILLED))
    except TrackingError as err:
        raise TrackingError(f"job {key}: {err}; nothing was computed, run the job again once the tracking store "
                            f"answers") from err
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
        raise _Terminated(f"terminated by signal {signum}")

    main = threading.current_thread() is threading.main_thread()
    previous = {s: signal.signal(s, _on_signal) for s in (signal.SIGTERM, signal.SIGINT)} if main else {}
    job: JobRun | None = None
    try:
        run = _retry(client.create_run, exp_id, tags=tags)
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
    for old in _runs_of(client, both, key, "FINISHED", workdir):
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
    names = [mlflow_cfg["experiment"], figures_experiment(mlflow_cfg["experiment"])]
    exps = [e for e in (_retry(client.get_experiment_by_name, n) for n in names) if e is not None]
    if not exps:
        return 0
    query = f"attributes.status = 'RUNNING' and tags.workdir = '{workdir or workdir_tag()}'"
    runs = _retry(client.search_runs, [e.experiment_id for e in exps], filter_string=query, max_results=10000)
    for run in runs:
        _retry(client.set_terminated, run.info.run_id, RunStatus.to_string(RunStatus.KILLED))
    return len(runs)


def start_workflow(mlflow_cfg: Mapping[str, Any]) -> list[str]:
    """What a workflow does with the store as it starts (Snakefile ``onstart``, before any job): adopt a SQLite store
    copied or moved with its tree (:func:`adopt_store`), then close the runs a SIGKILL left RUNNING
    (:func:`close_orphans`). Returns one line per thing done, for the log."""
    lines = []
    adopted = adopt_store(mlflow_cfg)
    if adopted:
        old, new = adopted["artifact_location"]
        came = (f"; {adopted['runs']} run(s) of {adopted['from']} (the tree it was copied from) are this tree's"
                if adopted["from"] else "")
        lines.append(f"the store's artifacts now go under {new} (it named {old}){came}")
    closed = close_orphans(mlflow_cfg=mlflow_cfg)
    if closed:
        lines.append(f"{closed} run(s) left RUNNING by an earlier, killed workflow are now KILLED")
    return lines


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
    _, both = _experiments(client, mlflow_cfg, "main")  # a figure shows main runs, the figures' runs, or both
    stages = [stage] if isinstance(stage, str) else list(stage)
    # tags allow no IN; the stages are chosen below
    query = f"attributes.status = 'FINISHED' and tags.workdir = '{workdir_tag()}'"
    if profile is not None:
        query += f" and tags.profile = '{profile}'"
    runs = _retry(client.search_runs, both, filter_string=query, max_results=50000)
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
