"""The extra runs behind the figures (workflow/rules/extra.smk): a method trained and evaluated under a variant
(its fleet size, demand intensity or dropout), with the main jobs' setup and steps (``dswm.pipeline.setup``,
``dswm.pipeline.jobs``), one MLflow run each in the figures' experiment.

* :func:`extra_train_job`     the model file and training manifest of a variant, as ``train_job`` writes them.
* :func:`extra_evaluate_job`  days.parquet (with a ``variant`` column), trajectory.npz and their content record, as
                              ``evaluate_job`` writes them, on the days of ``figures.eval_days``.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping, Sequence

import polars as pl

from dswm.config import build
from dswm.pipeline.jobs import evaluate_controller, finish_training, fit_on_training_days
from dswm.pipeline.setup import JobSetup, load_tensor, open_run, prepared_files_read, set_up
from dswm.protocol import evaluation
from dswm.settings import Display, EvalDayLimits, EvaluationSettings, Runtime
from prep.atomic import save_npz


def variant_run(s: JobSetup, *, mlflow_cfg: Mapping[str, Any], part: str, variant: str, dataset: str, method: str,
                seed: int, repo: str | Path, keep: Sequence[str | Path]):
    """The MLflow run of one extra job, in the figures' experiment (``kind`` "extra"), tagged ``stage`` "extra",
    ``variant`` and ``extra_job`` (``part``: train or evaluate); its job key
    (``extra/<variant>/<part>/<dataset>/<method>/seed<seed>``) is its own, so a rerun replaces only its own earlier
    run."""
    return open_run(s, mlflow_cfg=mlflow_cfg, stage=f"extra/{variant}/{part}", dataset=dataset, method=method,
                    seed=seed, repo=repo, keep=keep, kind="extra")


def extra_train_job(*, job: Mapping[str, Any], mlflow_cfg: Mapping[str, Any], variant: str, tensor_dir: str | Path,
                    dataset: str, method: str, seed: int, model_out: str | Path, manifest_out: str | Path,
                    run_dir: str | Path,
                    repo: str | Path, intensity: str | Path | None = None) -> dict:
    """Fit ``method`` on the training days of ``dataset`` under an extra run's variant (its fleet size or demand
    intensity); write the model file and the training manifest as ``dswm.pipeline.jobs.train_job`` does.

    Args:
        job: the plain form of ``dswm.settings.variant_train_slice`` (a u variant's factor in ``intensity_scale``).
        mlflow_cfg: the ``mlflow`` section (``dswm.settings.tracking``).
        variant: the variant's name (``K8``, ``u2``; an MLflow tag).
        intensity: the calibrate rule's record, when ``scenario.demand_intensity`` is ``calibrate``.

    Returns:
        The manifest written (without the loss history, which goes to MLflow).
    """
    s = set_up(job, "runtime", Runtime, intensity)
    data_files = prepared_files_read(tensor_dir)
    tensor = load_tensor(tensor_dir)
    with variant_run(s, mlflow_cfg=mlflow_cfg, part="train", variant=variant, dataset=dataset, method=method,
                     seed=seed, repo=repo, keep=[model_out, manifest_out]) as run:
        run.set_tags({"stage": "extra", "variant": variant, "extra_job": "train"})
        ctrl, manifest = fit_on_training_days(run, s, tensor=tensor, tensor_dir=tensor_dir, dataset=dataset,
                                              method=method, seed=seed, run_dir=run_dir)
        return finish_training(run, ctrl, manifest, method=method, model_out=model_out, manifest_out=manifest_out,
                               data_files=data_files, labels={"dataset": dataset, "method": method, "seed": seed},
                               extra={"variant": variant})


def extra_evaluate_job(*, job: Mapping[str, Any], mlflow_cfg: Mapping[str, Any], variant: str, display: Display,
                       tensor_dir: str | Path, dataset: str, method: str, seed: int, days_out: str | Path,
                       trajectory_out: str | Path,
                       record_out: str | Path, repo: str | Path, model: str | Path | None = None,
                       manifest: str | Path | None = None, intensity: str | Path | None = None,
                       reuse: Mapping[str, str | Path] | None = None) -> evaluation.EvalResult:
    """Evaluate one (dataset, method, seed) under an extra run's variant on the days of ``figures.eval_days``;
    write days.parquet, trajectory.npz and their content record as ``dswm.pipeline.jobs.evaluate_job`` does.

    Args:
        job: the plain form of ``dswm.settings.variant_evaluate_slice``.
        mlflow_cfg: the ``mlflow`` section (``dswm.settings.tracking``).
        variant: the variant's name (``do0.5``, ``K8``, ``u2``; an MLflow tag and a column of days.parquet).
        model, manifest: the model of the method's training source, trained by the main ``train`` rule when the
            variant's train slice is the main one's (a do variant), else by ``extra_train``.
        intensity: the calibrate rule's record, when ``scenario.demand_intensity`` is ``calibrate``.
        reuse: the same variant's run at the first of ``figures.seeds``, for a method whose result the seed does
            not change (as :func:`dswm.pipeline.jobs.evaluate_job`'s).
    """
    s = set_up(job, "evaluation", EvaluationSettings, intensity)
    limits = build(EvalDayLimits, s.job["eval_days"], "eval_days")
    tensor = load_tensor(tensor_dir)
    with variant_run(s, mlflow_cfg=mlflow_cfg, part="evaluate", variant=variant, dataset=dataset, method=method,
                     seed=seed, repo=repo, keep=[days_out, trajectory_out]) as run:
        run.set_tags({"stage": "extra", "variant": variant, "extra_job": "evaluate"})
        result, record, settings_record = evaluate_controller(
            run, s, tensor=tensor, tensor_dir=tensor_dir, limits=limits, dataset=dataset, method=method, seed=seed,
            display=display, model=model, manifest=manifest, what=f"{method} ({variant})", reuse=reuse)
        days = result.days.with_columns(pl.lit(variant).alias("variant"))
        evaluation.write_days(days, days_out, record, settings_record)
        save_npz(trajectory_out, **result.trajectories)
        run.log_metrics(evaluation.split_summary(days))
        run.set_tags({"data_source": tensor.meta["source"], "eval_days_hash": days["eval_days_hash"][0]})
        run.log_artifact(days_out)
    evaluation.write_eval_record(record_out, {"days.parquet": days_out, "trajectory.npz": trajectory_out})
    return result
