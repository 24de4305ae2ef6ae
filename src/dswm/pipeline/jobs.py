"""The workflow's jobs, wired from the library parts; each ``workflow/scripts/*.py`` calls one of these.

* :func:`train_job`     fit a learning method on the TRAINING days; model file + train_manifest.json (with the
                        SHA-256 of the checkpoint, the model file and every prepared file it read).
* :func:`evaluate_job`  evaluate one (dataset, method, seed); days.parquet (with the record of the model it
                        loaded: path, SHA-256, training source, and the record of the method's resolved
                        settings and BCD search) + trajectory.npz, then eval_manifest.json (the SHA-256 and
                        size of both, written last).
* :func:`calibrate_job` bisection of the demand intensity; a JSON with the value.
* :func:`tables_job`    the two tables from the result files.

Each job receives ``job``, the plain form of the settings slice its rule passes (``dswm.settings.*_slice``),
and builds its typed settings from it with the project's one builder; no job reads config.yaml.

Every output is written atomically (temp file, then rename), and training/evaluation jobs are tracked in
MLflow with exactly one run each.
"""
from __future__ import annotations

import json
import shlex
from pathlib import Path
from typing import Any, Mapping, Sequence

import torch

from dswm.config import build, stable_hash, to_plain
from dswm.methods import registry, snapshots
from dswm.methods.base import Controller
from dswm.pipeline import tracking
from dswm.pipeline.allocator import keep_freed_memory
from dswm.protocol import calibration, evaluation, selection, tables
from dswm.settings import (CalibrationSettings, Display, EvalDayLimits, EvaluationSettings, MethodSettings,
                           Runtime, SelectionSettings, calibrated_scenario)
from dswm.sim.core import FleetCore, core_from_tensor
from dswm.sim.scenario import Scenario
from prep.atomic import save_npz, write_json
from prep.rawio import sha256_file

DAY_METRICS = ("sr_mean", "energy_kj_per_slot", "energy_efficiency", "jain", "plan_ms_per_slot")


def _load_tensor(tensor_dir: str | Path):
    from prep.tensor import load

    return load(tensor_dir)


def _workdir_relative(path: str | Path) -> str:
    """``path`` relative to the working directory (the workflow's root, where the audit resolves it), POSIX."""
    p = Path(path)
    if p.is_absolute():
        try:
            p = p.relative_to(Path.cwd())
        except ValueError:
            pass
    return p.as_posix()


def prepared_files_read(tensor_dir: str | Path) -> list[dict]:
    """The ``data_files_read`` of a training manifest: the files ``prep.tensor.load`` reads from ``tensor_dir``.

    Returns:
        [{"path": path relative to the working directory, "sha256": hex SHA-256 of the file}] for
        demand.parquet and meta.json, hashed before the job loads them.
    """
    from prep.tensor import META_FILE, TENSOR_FILE

    return [{"path": _workdir_relative(Path(tensor_dir) / name), "sha256": sha256_file(Path(tensor_dir) / name)}
            for name in (TENSOR_FILE, META_FILE)]


def log_demand_input(run: tracking.JobRun, tensor_dir: str | Path, dataset: str, context: str) -> str:
    """Record the prepared demand tensor (``tensor_dir``/demand.parquet) as the run's MLflow dataset input, named
    ``dataset`` with the first 16 hex digits of its SHA-256 as digest; returns the full SHA-256."""
    from prep.tensor import TENSOR_FILE

    path = Path(tensor_dir) / TENSOR_FILE
    digest = sha256_file(path)
    run.log_dataset(path, name=dataset, digest=digest[:16], context=context)
    return digest


def _setup(runtime: Runtime | EvaluationSettings) -> None:
    torch.set_num_threads(runtime.torch_threads)
    keep_freed_memory()


def _common(job: Mapping[str, Any], key: str, cls: type,
            intensity: str | Path | None = None) -> tuple[Any, Scenario, MethodSettings]:
    """The typed ``job[key]`` (runtime or evaluation settings), scenario and method of a train, evaluate or select
    job; u is the calibrate rule's record ``intensity`` when the slice's scenario says ``calibrate``."""
    run = build(cls, job[key], key)
    _setup(run)
    scenario = calibrated_scenario(Scenario.from_dict(job["scenario"]), intensity)
    return run, scenario, MethodSettings.from_plain(job["method"], "method")


def _as_used(job: Mapping[str, Any], scenario: Scenario) -> dict:
    """``job`` with the scenario the job simulates (u as a number): what its MLflow run logs and hashes."""
    return {**job, "scenario": to_plain(scenario)}


def training_core(tensor, scenario: Scenario, device: str = "cpu") -> FleetCore:
    """A FleetCore over the TRAINING days only; ``core.day_ids`` maps its days to tensor day indices."""
    return core_from_tensor(tensor, scenario, tensor.train_days, device=device)


def train_job(*, job: Mapping[str, Any], mlflow_cfg: Mapping[str, Any], evaluated_as: list[str],
              tensor_dir: str | Path, dataset: str, method: str, seed: int, model_out: str | Path,
              manifest_out: str | Path, run_dir: str | Path, repo: str | Path, intensity: str | Path | None = None,
              history_out: str | Path | None = None, snapshots_out: str | Path | None = None) -> dict:
    """Fit ``method`` on the training days of ``dataset``; write the model file and the training manifest.

    Args:
        job: the plain form of ``dswm.settings.train_slice`` (the method carries its training settings only).
        mlflow_cfg: the ``mlflow`` section (``dswm.settings.tracking``): where the run is logged, not a rerun
            trigger.
        evaluated_as: the methods whose evaluations load this model (an MLflow tag).
        intensity: the calibrate rule's record, when ``scenario.demand_intensity`` is ``calibrate``.
        history_out: where the loss history is written as well (``dswm.pipeline.history.write_history``: one row
            per logged step, one column per series), the source of the training-diagnostics figure.
        snapshots_out: the train rule's ``snapshots`` directory: the model snapshots at the fractions of the
            budget that ``job["snapshots"]`` asks for, with their index (``dswm.methods.snapshots.export``); left
            empty when the slice asks for none.

    The manifest is what ``fit`` returns plus ``checkpoint_sha256`` (the checkpoint ``fit`` recorded, hashed when
    it returned), ``model``, ``model_sha256`` (``model_out`` once saved) and ``data_files_read``
    (:func:`prepared_files_read`); it is written last, so every file it hashes is complete (docs/ARCHITECTURE.md).

    Returns:
        The manifest written (without the loss history, which goes to MLflow).
    """
    ev, scenario, m = _common(job, "runtime", Runtime, intensity)
    job = _as_used(job, scenario)
    data_files = prepared_files_read(tensor_dir)
    tensor = _load_tensor(tensor_dir)
    with tracking.job_run(mlflow_cfg=mlflow_cfg, settings=job, stage="train", dataset=dataset,
                          method=method, seed=seed, config_hash=stable_hash(job, length=12), repo=repo,
                          keep=[p for p in (model_out, manifest_out, history_out) if p is not None]) as run:
        run.set_tags({"evaluated_as": ",".join(evaluated_as)})  # methods whose evaluations load this model
        log_demand_input(run, tensor_dir, dataset, "training")
        torch.manual_seed(seed)
        ctrl = registry.build(method, target=m.target, options=m.options, seed=seed, device=ev.device)
        core = training_core(tensor, scenario, device=ev.device)
        snaps = snapshots.for_train_job(job=job, method=method, seed=seed, run_dir=run_dir, data_files=data_files)
        manifest = dict(ctrl.fit(core, run_dir=run_dir, **({"snapshots": snaps} if snaps is not None else {})))

        def export_snapshots() -> None:
            if snapshots_out is not None and snapshots.export(snaps, snapshots_out, method=method, seed=seed):
                run.log_artifact(Path(snapshots_out) / snapshots.INDEX_FILE, "snapshots")

        return finish_training(run, ctrl, manifest, method=method, model_out=model_out, manifest_out=manifest_out,
                               data_files=data_files, history_out=history_out, after_save=export_snapshots,
                               labels={"dataset": dataset, "method": method, "seed": seed})


def finish_training(run: tracking.JobRun, ctrl: Controller, manifest: dict, *, method: str, model_out: str | Path,
                    manifest_out: str | Path, data_files: list[dict], history_out: str | Path | None = None,
                    after_save=None, labels: Mapping[str, Any], extra: Mapping[str, Any] | None = None) -> dict:
    """What every train job does once ``fit`` returned ``manifest``: log the loss history to MLflow (and write
    it to ``history_out``), hash the checkpoint, save the model, call ``after_save``, write the manifest with the
    model's and the read files' hashes (and ``extra``) last, and attach it to the run.

    Args:
        labels: {"dataset", "method", "seed"} of the history file's rows.

    Returns:
        The manifest written (without the loss history).
    """
    history = manifest.pop("history", None) or {}
    steps = history.pop("step", None)
    for name, values in history.items():
        run.log_series(name, values, steps)
    if history_out is not None:
        from dswm.pipeline.history import write_history

        write_history(history_out, history, steps, **labels)
    ckpt = manifest.get("checkpoint")
    if ckpt:
        if not Path(ckpt).is_file():
            raise FileNotFoundError(f"{manifest_out}: {method}.fit() recorded checkpoint {ckpt}, which does "
                                    f"not exist; expected the file training ended with")
        manifest["checkpoint_sha256"] = sha256_file(Path(ckpt))
    ctrl.save(model_out)
    if after_save is not None:
        after_save()
    manifest.setdefault("model", str(model_out))
    manifest.update(**(extra or {}), model_sha256=sha256_file(Path(model_out)), data_files_read=data_files)
    write_json(manifest_out, manifest)
    run.log_metrics({"train/n_transitions": float(manifest.get("n_transitions", 0)),
                     "train/steps": float(manifest.get("steps", 0))})
    run.log_artifact(manifest_out)
    return manifest


def load_source_model(run: tracking.JobRun, ctrl: Controller, m: MethodSettings, *, model: str | Path | None,
                      manifest: str | Path | None, what: str | None = None) -> dict:
    """Load the model of ``m``'s training source into ``ctrl`` when the method learns, after checking its hash
    (:func:`model_record`), and tag the run with it; returns the model record (the empty one for a method that does
    not learn).

    Raises:
        ValueError: a learning method without its source's model file or manifest (``what`` names the job).
    """
    if not ctrl.learns:
        return model_record(method=m.name)
    if model is None or manifest is None:
        raise ValueError(f"{what or m.name}: a learning method needs its training source's model file and "
                         f"train_manifest.json (found model={model!r}, manifest={manifest!r})")
    record = model_record(method=m.name, source=m.training_source or m.name, model=model, manifest=manifest)
    run.set_tags({"train_source": record["train_source"], "model_path": record["model"],
                  "model_sha256": record["model_sha256"]})
    ctrl.load(model)
    return record


def model_record(*, method: str, source: str | None = None, model: str | Path | None = None,
                 manifest: str | Path | None = None) -> dict:
    """What an evaluation records about the model it loads (``evaluation.MODEL_RECORD_FIELDS``).

    Args:
        method: the evaluated method.
        source: its training source (dswm.methods.registry.training_sources); None for a method that does not learn.
        model: the source's model file, hashed here, before it is loaded.
        manifest: the source's train_manifest.json; its ``model_sha256`` must be the model file's SHA-256.

    Raises:
        ValueError: the model file does not hash to the manifest's ``model_sha256``.
    """
    if source is None:
        return {"method": method, "train_source": None, "model": None, "model_sha256": None, "train_manifest": None}
    found = sha256_file(Path(model))
    with open(manifest, encoding="utf-8") as fh:
        want = json.load(fh).get("model_sha256")
    if found != want:  # a truncated or replaced file; the train job that writes it rebuilds it
        rel = shlex.quote(_workdir_relative(model))
        raise ValueError(f"{model}: SHA-256 is {found}, expected {want} (model_sha256 of {manifest}) — not the model "
                         f"{source} trained for {method}; re-run the train job of {source}: `rm {rel}`, then the same "
                         f"snakemake command again (or add `--forcerun {rel}` to it)")
    return {"method": method, "train_source": source, "model": _workdir_relative(model), "model_sha256": found,
            "train_manifest": _workdir_relative(manifest)}


def evaluate_job(*, job: Mapping[str, Any], mlflow_cfg: Mapping[str, Any], display: Display,
                 tensor_dir: str | Path, dataset: str, method: str, seed: int, days_out: str | Path,
                 trajectory_out: str | Path, record_out: str | Path, repo: str | Path,
                 model: str | Path | None = None, manifest: str | Path | None = None,
                 intensity: str | Path | None = None) -> evaluation.EvalResult:
    """Evaluate one (dataset, method, seed) job; write days.parquet and trajectory.npz, then their content record
    ``record_out``; track it in MLflow.

    Args:
        job: the plain form of ``dswm.settings.evaluate_slice``.
        mlflow_cfg: the ``mlflow`` section (``dswm.settings.tracking``): where the run is logged, not a rerun
            trigger.
        display: how the job reports progress (not part of its rerun trigger).
        intensity: the calibrate rule's record, when ``scenario.demand_intensity`` is ``calibrate``.

    A learning method loads ``model``, the model of its training source, and ``manifest``, that source's
    training manifest. days.parquet records the model (:func:`model_record`) and the method's resolved settings
    with the BCD search it runs (:func:`method_record`) in its metadata; the MLflow run is tagged ``train_source``,
    ``model_path`` and ``model_sha256``. ``record_out`` (``evaluation.write_eval_record``: the SHA-256 and size of
    days.parquet and trajectory.npz) is written last, once both are complete and logged; the audit
    (``protocol.result_records``) proves from it that neither changed since.
    """
    ev, scenario, m = _common(job, "evaluation", EvaluationSettings, intensity)
    job = _as_used(job, scenario)
    limits = build(EvalDayLimits, job["eval_days"], "eval_days")
    tensor = _load_tensor(tensor_dir)
    with tracking.job_run(mlflow_cfg=mlflow_cfg, settings=job, stage="evaluate", dataset=dataset,
                          method=method, seed=seed, config_hash=stable_hash(job, length=12), repo=repo,
                          keep=[days_out, trajectory_out]) as run:
        log_demand_input(run, tensor_dir, dataset, "evaluation")
        ctrl = registry.build(method, target=m.target, options=m.options, seed=seed, device=ev.device)
        record = load_source_model(run, ctrl, m, model=model, manifest=manifest)
        settings_record = method_record(m, ctrl)
        result = evaluation.evaluate(tensor=tensor, controller=ctrl, scenario=scenario, seed=seed,
                                     limits={"id": limits.id, "ood": limits.ood}, profile=job["profile"],
                                     device=ev.device, batch_days=ev.batch_days,
                                     progress_interval_s=display.progress_mininterval_s)
        evaluation.write_days(result.days, days_out, record, settings_record)
        save_npz(trajectory_out, **result.trajectories)
        logged = [*DAY_METRICS, *evaluation.stat_columns(result.days)]
        for row in result.days.iter_rows(named=True):
            run.log_metrics({f"day/{k}": row[k] for k in logged if row[k] is not None}, step=row["day"])
        run.log_metrics(evaluation.split_summary(result.days))
        run.set_tags({"data_source": tensor.meta["source"], "eval_days_hash": result.days["eval_days_hash"][0],
                      "obs_spec_hash": result.days["obs_spec_hash"][0]})
        run.log_artifact(days_out)
        run.log_artifact(trajectory_out)
    evaluation.write_eval_record(record_out, {"days.parquet": days_out, "trajectory.npz": trajectory_out})
    return result


def method_record(m: MethodSettings, ctrl: Controller) -> dict:
    """What an evaluation records about the method it ran (``evaluation.METHOD_RECORD_FIELDS``).

    Args:
        m: the method's registration and typed settings (``MethodSettings`` of the job's slice).
        ctrl: the controller built from ``m``; its ``search_settings()`` is the BCD search it runs, or None.

    Returns:
        {"method": m.name, "class": m.target, "options": plain ``m.options``, "search": plain search settings or
        None}, every value plain JSON (``dswm.config.to_plain``).
    """
    search = ctrl.search_settings()
    return {"method": m.name, "class": m.target, "options": to_plain(m.options),
            "search": None if search is None else to_plain(search)}


def calibrate_job(*, job: Mapping[str, Any], tensor_dir: str | Path, out: str | Path) -> dict:
    """Bisection of the demand intensity (see dswm.protocol.calibration); writes and returns the JSON report.

    Args:
        job: the plain form of ``dswm.settings.calibrate_slice`` (the scenario less its demand intensity).
    """
    ev = build(Runtime, job["runtime"], "runtime")
    _setup(ev)
    cal = build(CalibrationSettings, job["calibration"], "calibration")
    # The value being calibrated is not an input: the bracket's lower end stands in until bisection sets it.
    scenario = Scenario.from_dict({**job["scenario"], "demand_intensity": cal.bracket[0]})
    tensor = _load_tensor(tensor_dir)
    report = calibration.calibrate(tensor=tensor, scenario=scenario, target=cal.target_served_ratio,
                                   bracket=cal.bracket, tolerance=cal.tolerance, max_iter=cal.max_iter,
                                   device=ev.device)
    write_json(out, report)
    return report


def tables_job(*, job: Mapping[str, Any], result_paths: Sequence[str | Path], meta_paths: Mapping[str, str | Path],
               out_dir: str | Path, database: str | Path | None = None) -> dict:
    """Build <tables.main_dataset>_main and cross_dataset (md, tex, csv) from the result files, and the DuckDB
    database of views over them (``results/results.duckdb``) when `database` is given.

    Args:
        job: the plain form of ``dswm.settings.tables_slice``.
    """
    specs = {m["name"]: build(registry.MethodSpec, m, f"methods.{m['name']}") for m in job["methods"]}
    return tables.build_tables(result_paths=result_paths, meta_paths=meta_paths, specs=specs,
                               run_order=[m["name"] for m in job["methods"]], tables_cfg=job["tables"],
                               profile=job["profile"], out_dir=out_dir, database=database)


def select_job(*, job: Mapping[str, Any], display: Display, tensor_dir: str | Path, out: str | Path,
               run_dir: str | Path, intensity: str | Path | None = None) -> dict:
    """Choose the shared search's strength and the planner's open values on TRAINING days
    (``dswm.protocol.selection``); write and return the JSON report.

    Args:
        job: the plain form of ``dswm.settings.select_slice``.
        display: how the job reports progress.
        run_dir: where the selection's world model writes its checkpoint.
        intensity: the calibrate rule's record, when ``scenario.demand_intensity`` is ``calibrate``.
    """
    ev, scenario, m = _common(job, "evaluation", EvaluationSettings, intensity)
    sel = build(SelectionSettings, job["selection"], "selection")
    tensor = _load_tensor(tensor_dir)
    fit_days, val_days = selection.split_training_days(tensor, sel.fit_days)
    score_kw = {"tensor": tensor, "scenario": scenario, "days": val_days, "seed": 0, "device": ev.device,
                "batch_days": ev.batch_days, "progress_interval_s": display.progress_mininterval_s}
    greedy = registry.BUILTIN["greedy"].target
    search = selection.select_search(
        make=lambda cand: registry.build("greedy", target=greedy, options=cand, seed=0, device=ev.device),
        candidates=sel.search_candidates, budget_ms=sel.search_budget_ms, **score_kw)
    torch.manual_seed(0)
    ctrl = registry.build(m.name, target=m.target, options=m.options, seed=0, device=ev.device)
    planner = selection.select_planner(controller=ctrl, fit_days=fit_days, gammas=sel.gamma, sigma0s=sel.sigma0,
                                       run_dir=run_dir, **score_kw)
    report = {"dataset": tensor.meta["dataset"], "profile": job["profile"], "torch_threads": ev.torch_threads,
              "validation_days": [tensor.labels[d] for d in val_days], "search": search, "planner": planner}
    write_json(out, report)
    return report


# ---- the extra runs behind the figures (workflow/rules/extra.smk) ---------------------------------------------
import polars as pl  # noqa: E402

from dswm.settings import scale_intensity  # noqa: E402


def _variant_run(*, job: Mapping[str, Any], mlflow_cfg: Mapping[str, Any], part: str, variant: str, dataset: str,
                 method: str, seed: int, repo: str | Path, keep: Sequence[str | Path]):
    """The MLflow run of one extra job, in the figures' experiment (``kind`` "extra"): tagged ``stage`` "extra",
    ``variant`` and ``extra_job`` (``part``: train or evaluate); its job key
    (``extra/<variant>/<part>/<dataset>/<method>/seed<seed>``) is its own, so a rerun replaces only its own earlier
    run."""
    return tracking.job_run(mlflow_cfg=mlflow_cfg, settings=job, stage=f"extra/{variant}/{part}",
                            dataset=dataset, method=method, seed=seed, config_hash=stable_hash(job, length=12),
                            repo=repo, keep=keep, kind="extra")


def _variant_common(job: Mapping[str, Any], key: str, cls: type,
                    intensity: str | Path | None) -> tuple[Any, Scenario, MethodSettings]:
    """:func:`_common` with a u variant's factor applied to the calibrated u (``job["intensity_scale"]``)."""
    run, scenario, m = _common(job, key, cls, intensity)
    return run, scale_intensity(scenario, float(job.get("intensity_scale", 1.0))), m


def extra_train_job(*, job: Mapping[str, Any], mlflow_cfg: Mapping[str, Any], variant: str, tensor_dir: str | Path,
                    dataset: str, method: str, seed: int, model_out: str | Path, manifest_out: str | Path,
                    run_dir: str | Path,
                    repo: str | Path, intensity: str | Path | None = None) -> dict:
    """Fit ``method`` on the training days of ``dataset`` under an extra run's variant (its fleet size or demand
    intensity); write the model file and the training manifest as :func:`train_job` does.

    Args:
        job: the plain form of ``dswm.settings.variant_train_slice``.
        mlflow_cfg: the ``mlflow`` section (``dswm.settings.tracking``).
        variant: the variant's name (``K8``, ``u2``; an MLflow tag).
        intensity: the calibrate rule's record, when ``scenario.demand_intensity`` is ``calibrate``.

    Returns:
        The manifest written (without the loss history, which goes to MLflow).
    """
    ev, scenario, m = _variant_common(job, "runtime", Runtime, intensity)
    job = _as_used(job, scenario)
    data_files = prepared_files_read(tensor_dir)
    tensor = _load_tensor(tensor_dir)
    with _variant_run(job=job, mlflow_cfg=mlflow_cfg, part="train", variant=variant, dataset=dataset, method=method,
                      seed=seed, repo=repo, keep=[model_out, manifest_out]) as run:
        run.set_tags({"stage": "extra", "variant": variant, "extra_job": "train"})
        log_demand_input(run, tensor_dir, dataset, "training")
        torch.manual_seed(seed)
        ctrl = registry.build(method, target=m.target, options=m.options, seed=seed, device=ev.device)
        manifest = dict(ctrl.fit(training_core(tensor, scenario, device=ev.device), run_dir=run_dir))
        return finish_training(run, ctrl, manifest, method=method, model_out=model_out, manifest_out=manifest_out,
                               data_files=data_files, labels={"dataset": dataset, "method": method, "seed": seed},
                               extra={"variant": variant})


def extra_evaluate_job(*, job: Mapping[str, Any], mlflow_cfg: Mapping[str, Any], variant: str, display: Display,
                       tensor_dir: str | Path, dataset: str, method: str, seed: int, days_out: str | Path,
                       trajectory_out: str | Path,
                       record_out: str | Path, repo: str | Path, model: str | Path | None = None,
                       manifest: str | Path | None = None,
                       intensity: str | Path | None = None) -> evaluation.EvalResult:
    """Evaluate one (dataset, method, seed) under an extra run's variant on the days of ``figures.eval_days``;
    write days.parquet, trajectory.npz and their content record as :func:`evaluate_job` does.

    Args:
        job: the plain form of ``dswm.settings.variant_evaluate_slice``.
        mlflow_cfg: the ``mlflow`` section (``dswm.settings.tracking``).
        variant: the variant's name (``do0.5``, ``K8``, ``u2``; an MLflow tag and a column of days.parquet).
        model, manifest: the model of the method's training source, trained by the main ``train`` rule when the
            variant's train slice is the main one's (a do variant), else by ``extra_train``.
        intensity: the calibrate rule's record, when ``scenario.demand_intensity`` is ``calibrate``.
    """
    ev, scenario, m = _variant_common(job, "evaluation", EvaluationSettings, intensity)
    job = _as_used(job, scenario)
    limits = build(EvalDayLimits, job["eval_days"], "eval_days")
    tensor = _load_tensor(tensor_dir)
    with _variant_run(job=job, mlflow_cfg=mlflow_cfg, part="evaluate", variant=variant, dataset=dataset,
                      method=method, seed=seed, repo=repo, keep=[days_out, trajectory_out]) as run:
        run.set_tags({"stage": "extra", "variant": variant, "extra_job": "evaluate"})
        log_demand_input(run, tensor_dir, dataset, "evaluation")
        ctrl = registry.build(method, target=m.target, options=m.options, seed=seed, device=ev.device)
        record = load_source_model(run, ctrl, m, model=model, manifest=manifest, what=f"{method} ({variant})")
        result = evaluation.evaluate(tensor=tensor, controller=ctrl, scenario=scenario, seed=seed,
                                     limits={"id": limits.id, "ood": limits.ood}, profile=job["profile"],
                                     device=ev.device, batch_days=ev.batch_days,
                                     progress_interval_s=display.progress_mininterval_s)
        days = result.days.with_columns(pl.lit(variant).alias("variant"))
        evaluation.write_days(days, days_out, record, method_record(m, ctrl))
        save_npz(trajectory_out, **result.trajectories)
        run.log_metrics(evaluation.split_summary(days))
        run.set_tags({"data_source": tensor.meta["source"], "eval_days_hash": days["eval_days_hash"][0]})
        run.log_artifact(days_out)
    evaluation.write_eval_record(record_out, {"days.parquet": days_out, "trajectory.npz": trajectory_out})
    return result
