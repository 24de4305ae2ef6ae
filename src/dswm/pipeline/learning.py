"""The learning curves' jobs (workflow/rules/learning.smk), with the main jobs' setup and steps
(``dswm.pipeline.setup``, ``dswm.pipeline.jobs``), one MLflow run each in the figures' experiment (kind "learning").

* :func:`learning_train_job`  ONE run of a learner at its cap on the training days less the validation days
                              (``dswm.protocol.learning.learning_days``): model, manifest, loss history, and the
                              snapshots of the untrained model and of every ladder fraction.
* :func:`learning_score_job`  every snapshot of that run (a reference method: the method itself) on the validation
                              days, in the evaluation's own environment and initial fleet: curve.parquet, one row per
                              (snapshot, day), ``split`` "validation".
"""
from __future__ import annotations

import sys
from pathlib import Path
from typing import Any, Mapping

import polars as pl

from dswm.methods import snapshots
from dswm.pipeline.jobs import finish_training, fit_on_training_days
from dswm.pipeline.setup import (load_tensor, open_run, prepared_files_read, score_snapshot, set_up,
                                 workdir_relative)
from dswm.protocol.learning import VALIDATION_SPLIT, learning_days
from dswm.settings import Display, EvaluationSettings, Runtime
from prep.atomic import atomic_path

CURVE_COLUMNS = ("fraction", "untrained", "done", "total", "n_transitions", "gradient_steps", "snapshot",
                 "snapshot_sha256")
"""The columns a score file adds to the evaluation's per-day columns (null for a reference method but ``untrained``,
false)."""


def learning_train_job(*, job: Mapping[str, Any], mlflow_cfg: Mapping[str, Any], tensor_dir: str | Path,
                       dataset: str, method: str, seed: int, model_out: str | Path, manifest_out: str | Path,
                       history_out: str | Path, snapshots_out: str | Path, run_dir: str | Path, repo: str | Path,
                       intensity: str | Path | None = None) -> dict:
    """Fit ``method`` at its cap on the training days of ``dataset`` less the validation days, taking the snapshots
    of ``job["snapshots"]`` (the untrained model and the ladder); write them with their index, the model file, the
    loss history and the training manifest (with ``validation_days``, the labels held out), as ``train_job`` does.

    Args:
        job: the plain form of ``dswm.settings.learning_train_slice``.
        mlflow_cfg: the ``mlflow`` section (``dswm.settings.tracking``).
        intensity: the calibrate rule's record, when ``scenario.demand_intensity`` is ``calibrate``.

    Returns:
        The manifest written (without the loss history).
    """
    s = set_up(job, "runtime", Runtime, intensity)
    data_files = prepared_files_read(tensor_dir)
    tensor = load_tensor(tensor_dir)
    fit, val = learning_days(tensor, int(job["validation_days"]))
    held = [tensor.labels[d] for d in val]
    with open_run(s, mlflow_cfg=mlflow_cfg, stage="learning/train", dataset=dataset, method=method, seed=seed,
                  repo=repo, keep=[model_out, manifest_out, history_out], kind="learning") as run:
        run.set_tags({"stage": "learning", "learning_job": "train", "validation_days": ",".join(held)})
        snaps = snapshots.for_train_job(job=s.job, method=method, seed=seed, run_dir=run_dir, data_files=data_files)
        ctrl, manifest = fit_on_training_days(run, s, tensor=tensor, tensor_dir=tensor_dir, dataset=dataset,
                                              method=method, seed=seed, run_dir=run_dir, snaps=snaps, days=fit)

        def export_snapshots() -> None:
            snapshots.export(snaps, snapshots_out, method=method, seed=seed)
            run.log_artifact(Path(snapshots_out) / snapshots.INDEX_FILE, "snapshots")

        return finish_training(run, ctrl, manifest, method=method, model_out=model_out, manifest_out=manifest_out,
                               data_files=data_files, history_out=history_out, after_save=export_snapshots,
                               labels={"dataset": dataset, "method": method, "seed": seed},
                               extra={"validation_days": held})


def learning_score_job(*, job: Mapping[str, Any], mlflow_cfg: Mapping[str, Any], display: Display,
                       tensor_dir: str | Path, dataset: str, method: str, seed: int, out: str | Path,
                       repo: str | Path, snapshots_dir: str | Path | None = None,
                       intensity: str | Path | None = None) -> pl.DataFrame:
    """Score every snapshot of ``snapshots_dir`` (None: ``method`` itself, a method without training) on the
    validation days; write ``out`` (curve.parquet) and log each snapshot's mean served ratio against the
    transitions consumed (metric ``learning/sr_mean``).

    Each snapshot is loaded into a fresh controller and evaluated alone (the evaluation seeds torch and numpy with
    ``seed`` each time), so a snapshot's number does not depend on the others; snapshots that share a file (ladder
    fractions reached at the same unit) share their scores.

    Returns:
        The score rows: the evaluation's per-day columns (``split`` "validation") and :data:`CURVE_COLUMNS`, in
        ladder order, the untrained snapshot first.
    """
    s = set_up(job, "evaluation", EvaluationSettings, intensity)
    tensor = load_tensor(tensor_dir)
    _, val = learning_days(tensor, int(job["validation_days"]))
    entries = snapshots.read_index(snapshots_dir) if snapshots_dir is not None else [None]
    with open_run(s, mlflow_cfg=mlflow_cfg, stage="learning/score", dataset=dataset, method=method, seed=seed,
                  repo=repo, keep=[out], kind="learning") as run:
        run.set_tags({"stage": "learning", "learning_job": "score", "diagnostic_only": "true",
                      "validation_days": ",".join(tensor.labels[d] for d in val)})
        scored: dict[str | None, pl.DataFrame] = {}
        frames = []
        for e in entries:
            key = None if e is None else e["sha256"]
            if key not in scored:
                print(f"learning_score: {method}" + ("" if e is None else f", snapshot at fraction {e['fraction']:g} "
                      f"of the cap ({e['n_transitions']} transitions)"), file=sys.stderr)
                scored[key] = score_snapshot(s, tensor=tensor, method=method, seed=seed,
                                             path=None if e is None else e["path"], days={VALIDATION_SPLIT: val},
                                             progress_interval_s=display.progress_mininterval_s)
            frames.append(scored[key].with_columns(**{k: pl.lit(v) for k, v in _curve_marks(e).items()}))
            if e is not None:
                run.log_metrics({"learning/sr_mean": float(scored[key]["sr_mean"].mean())},
                                step=int(e["n_transitions"]))
        frame = pl.concat(frames, how="vertical_relaxed").with_columns(
            pl.col("day").cast(pl.Int32), pl.col("seed").cast(pl.Int32), pl.col("fraction").cast(pl.Float64),
            pl.col("done", "total", "n_transitions", "gradient_steps").cast(pl.Int64),
            pl.col("snapshot", "snapshot_sha256").cast(pl.String))
        with atomic_path(out) as tmp:
            frame.write_parquet(tmp)
        run.log_artifact(out)
    return frame


def _curve_marks(entry: Mapping[str, Any] | None) -> dict:
    """The :data:`CURVE_COLUMNS` of one snapshot index entry (None: a reference method, no snapshot)."""
    if entry is None:
        return {"fraction": None, "untrained": False, "done": None, "total": None, "n_transitions": None,
                "gradient_steps": None, "snapshot": None, "snapshot_sha256": None}
    return {"fraction": float(entry["fraction"]), "untrained": float(entry["fraction"]) == 0.0,
            "done": int(entry["done"]), "total": int(entry["total"]), "n_transitions": int(entry["n_transitions"]),
            "gradient_steps": entry.get("gradient_steps"), "snapshot": workdir_relative(entry["path"]),
            "snapshot_sha256": entry["sha256"]}
