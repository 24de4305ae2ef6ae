"""The store and its two experiments: created once (:func:`init_store`, the ``mlflow_init`` rule), made this tree's
own after the tree was copied or moved (:func:`adopt_store`), and tidied as a workflow starts (:func:`start_workflow`:
orphaned runs closed)."""
from __future__ import annotations

import contextlib
import sqlite3
from pathlib import Path
from typing import Any, Mapping
from urllib.parse import unquote, urlparse

from mlflow.entities import RunStatus
from mlflow.tracking import MlflowClient

from dswm.pipeline.tracking.client import (TrackingAuthError, TrackingError, client_for, retry, sqlite_uri,
                                           tracking_uri, uses_server, workdir_tag)

EXPERIMENT_KIND = ("mlflow.experimentKind", "custom_model_development")
"""The experiment tag that makes the MLflow UI open on the training-runs view (without it, MLflow 3 opens on
the GenAI overview, whose traces page this project never fills)."""

RUN_KINDS = {
    "main": "a train or evaluate job of the tables (the workflow's `tables` target)",
    "extra": "an extra run behind a figure (do(s) probe, scaling sweeps; workflow/rules/extra.smk)",
    "probe": "the sample-efficiency probe of a train job's snapshots (workflow/rules/probes.smk)",
    "wm_quality": "the world-model quality replay of a DSWM model (workflow/rules/wm.smk)",
    "learning": "a learning-curve run: a learner at its cap and its snapshots on validation days "
                "(workflow/rules/learning.smk)",
}
"""The ``kind`` tag of a run -> what the run is. The main runs go to the experiment ``mlflow.experiment``; the
others, which only the figures use, to :func:`figures_experiment`, so the UI opens on the tables' runs alone."""
FIGURES_SUFFIX = "-figures"
"""The figures' experiment is named after the main one with this suffix (``dswm`` -> ``dswm-figures``)."""
EXPERIMENT_NOTES = {
    "main": "The runs of the tables: one train or evaluate run per job (tag kind = main). The runs behind the "
            "figures only are in the experiment '{figures}'.",
    "figures": "The runs behind the figures only, none a table's source: extra runs, the sample-efficiency probe, "
               "the world-model quality replay and the learning curves (tag kind = extra, probe, wm_quality or "
               "learning). The tables' runs are "
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
    found = retry(client.get_experiment_by_name, names[part])
    if found is None:
        try:
            exp_id = retry(client.create_experiment, names[part], artifact_location=location)
        except TrackingAuthError:
            raise
        except TrackingError:  # another workflow (or job) on the same store created it first
            found = retry(client.get_experiment_by_name, names[part])
            if found is None:
                raise
    if found is not None:
        exp_id = found.experiment_id
        if found.lifecycle_stage == "deleted":
            retry(client.restore_experiment, exp_id)
    retry(client.set_experiment_tag, exp_id, *EXPERIMENT_KIND)
    retry(client.set_experiment_tag, exp_id, "mlflow.note.content", EXPERIMENT_NOTES[part].format(**names))
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
    exp = retry(client.get_experiment, ids["main"])
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


def store_client(mlflow_cfg: Mapping[str, Any]) -> MlflowClient:
    """:func:`client_for`, once the SQLite store is known to exist (a client would create an empty one)."""
    if not uses_server(mlflow_cfg) and not Path(mlflow_cfg["store"]).exists():
        raise FileNotFoundError(f"{mlflow_cfg['store']}: MLflow store missing; it is created by the mlflow_init rule "
                                f"(run `snakemake --cores 1 --forcerun mlflow_init mlflow_init`)")
    return client_for(mlflow_cfg)


def main_experiment(client: MlflowClient, mlflow_cfg: Mapping[str, Any]):
    """The configured (main) experiment, checked to exist (the mlflow_init rule creates it)."""
    exp = retry(client.get_experiment_by_name, mlflow_cfg["experiment"])
    if exp is None:
        raise LookupError(f"{tracking_uri(mlflow_cfg)}: experiment {mlflow_cfg['experiment']!r} missing; the "
                          f"mlflow_init rule creates it")
    return exp


def run_experiments(client: MlflowClient, mlflow_cfg: Mapping[str, Any], kind: str) -> tuple[str, list[str]]:
    """(the id of the experiment a run of ``kind`` goes to, the ids of both experiments that exist).

    The main experiment must exist (the mlflow_init rule creates it); the figures' experiment, which mlflow_init
    creates too, is created here when a store made before it lacks it (same artifact location as the main one)."""
    target = experiment_of(mlflow_cfg, kind)
    main = main_experiment(client, mlflow_cfg)
    figures = retry(client.get_experiment_by_name, figures_experiment(main.name))
    if target != main.name and (figures is None or figures.lifecycle_stage == "deleted"):
        fid = _ensure_experiment(client, main.name, "figures", main.artifact_location)
    else:
        fid = figures.experiment_id if figures is not None else None
    return (main.experiment_id if target == main.name else fid), [i for i in (main.experiment_id, fid) if i]


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
    exps = [e for e in (retry(client.get_experiment_by_name, n) for n in names) if e is not None]
    if not exps:
        return 0
    query = f"attributes.status = 'RUNNING' and tags.workdir = '{workdir or workdir_tag()}'"
    runs = retry(client.search_runs, [e.experiment_id for e in exps], filter_string=query, max_results=10000)
    for run in runs:
        retry(client.set_terminated, run.info.run_id, RunStatus.to_string(RunStatus.KILLED))
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
