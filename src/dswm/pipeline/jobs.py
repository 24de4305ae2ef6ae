"""The workflow's jobs, wired from the library parts; each ``workflow/scripts/*.py`` calls one of these.

* :func:`train_job`     fit a learning method on the TRAINING days; model file + train_manifest.json (with the
                        SHA-256 of the checkpoint, the model file and every prepared file it read).
* :func:`evaluate_job`  evaluate one (dataset, method, seed); days.parquet (with the record of the model it
                        loaded: path, SHA-256, training source, and the record of the method's resolved
                        settings and BCD search) + trajectory.npz, then eval_manifest.json (the SHA-256 and
                        size of both, written last).
* :func:`calibrate_job` bisection of the demand intensity; a JSON with the value.
* :func:`tables_job`    the two tables from the result files.
* :func:`select_job`    the shared search's strength and the planner's open values, chosen on training days.

Every job that simulates is set up by ``dswm.pipeline.setup`` (as are the extra runs, the probe and the world-model
quality job); :func:`fit_on_training_days`, :func:`finish_training` and :func:`evaluate_controller` are the steps
every train and evaluate job takes, the extra runs' included (``dswm.pipeline.extra``).

Each job receives ``job``, the plain form of the settings slice its rule passes (``dswm.settings.*_slice``),
and builds its typed settings from it with the project's one builder; no job reads config.yaml.

Every output is written atomically (temp file, then rename), and training/evaluation jobs are tracked in
MLflow with exactly one run each.
"""
from __future__ import annotations

import sys
from pathlib import Path
from typing import Any, Mapping, Sequence

import torch

from dswm.config import build
from dswm.methods import registry, snapshots
from dswm.methods.base import Controller
from dswm.pipeline import tracking
from dswm.pipeline.setup import (JobSetup, build_controller, init_process, load_source_model, load_tensor,
                                 log_demand_input, method_record, open_run, prepared_files_read, set_up,
                                 training_core)
from dswm.protocol import calibration, evaluation, selection, tables
from dswm.protocol.reuse import reuse_evaluation
from dswm.settings import (REUSED_FILES, CalibrationSettings, Display, EvalDayLimits, EvaluationSettings, Runtime,
                           SelectionSettings)
from dswm.sim.scenario import Scenario
from prep.atomic import save_npz, write_json
from prep.rawio import sha256_file

DAY_METRICS = ("sr_mean", "energy_kj_per_slot", "energy_efficiency", "jain", "plan_ms_per_slot")


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
    s = set_up(job, "runtime", Runtime, intensity)
    data_files = prepared_files_read(tensor_dir)
    tensor = load_tensor(tensor_dir)
    with open_run(s, mlflow_cfg=mlflow_cfg, stage="train", dataset=dataset, method=method, seed=seed, repo=repo,
                  keep=[p for p in (model_out, manifest_out, history_out) if p is not None]) as run:
        run.set_tags({"evaluated_as": ",".join(evaluated_as)})  # methods whose evaluations load this model
        snaps = snapshots.for_train_job(job=s.job, method=method, seed=seed, run_dir=run_dir, data_files=data_files)
        ctrl, manifest = fit_on_training_days(run, s, tensor=tensor, tensor_dir=tensor_dir, dataset=dataset,
                                              method=method, seed=seed, run_dir=run_dir, snaps=snaps)

        def export_snapshots() -> None:
            if snapshots_out is not None and snapshots.export(snaps, snapshots_out, method=method, seed=seed):
                run.log_artifact(Path(snapshots_out) / snapshots.INDEX_FILE, "snapshots")

        return finish_training(run, ctrl, manifest, method=method, model_out=model_out, manifest_out=manifest_out,
                               data_files=data_files, history_out=history_out, after_save=export_snapshots,
                               labels={"dataset": dataset, "method": method, "seed": seed})


def fit_on_training_days(run: tracking.JobRun, s: JobSetup, *, tensor, tensor_dir: str | Path, dataset: str,
                         method: str, seed: int, run_dir: str | Path, snaps: snapshots.Snapshots | None = None,
                         days: Sequence[int] | None = None) -> tuple[Controller, dict]:
    """What every train job does inside its run before :func:`finish_training`: record the demand tensor as the
    run's input, seed torch with ``seed``, build the controller and ``fit`` it on the TRAINING days
    (:func:`dswm.pipeline.setup.training_core`; ``days``: those of them, a learning run's), passing ``snaps``
    (``dswm.methods.snapshots.for_train_job``) when there are any.

    Returns:
        (the fitted controller, a copy of what ``fit`` returned).
    """
    log_demand_input(run, tensor_dir, dataset, "training")
    torch.manual_seed(seed)
    ctrl = build_controller(s, method, seed)
    core = training_core(tensor, s.scenario, device=s.settings.device, days=days)
    manifest = dict(ctrl.fit(core, run_dir=run_dir, **({"snapshots": snaps} if snaps is not None else {})))
    return ctrl, manifest


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


def reused_inputs(inputs) -> dict[str, str] | None:
    """{"days", "trajectory", "record"} of the evaluation a job's Snakemake ``inputs`` name to reuse, or None."""
    return {k: inputs[f"reuse_{k}"] for k in REUSED_FILES} if "reuse_days" in inputs.keys() else None


def evaluate_job(*, job: Mapping[str, Any], mlflow_cfg: Mapping[str, Any], display: Display,
                 tensor_dir: str | Path, dataset: str, method: str, seed: int, days_out: str | Path,
                 trajectory_out: str | Path, record_out: str | Path, repo: str | Path,
                 model: str | Path | None = None, manifest: str | Path | None = None,
                 intensity: str | Path | None = None,
                 reuse: Mapping[str, str | Path] | None = None) -> evaluation.EvalResult:
    """Evaluate one (dataset, method, seed) job; write days.parquet and trajectory.npz, then their content record
    ``record_out``; track it in MLflow.

    Args:
        job: the plain form of ``dswm.settings.evaluate_slice``.
        mlflow_cfg: the ``mlflow`` section (``dswm.settings.tracking``): where the run is logged, not a rerun
            trigger.
        display: how the job reports progress (not part of its rerun trigger).
        intensity: the calibrate rule's record, when ``scenario.demand_intensity`` is ``calibrate``.
        reuse: {"days", "trajectory", "record"} of the dataset's first seed's evaluation of a method whose result
            the seed does not change (``dswm.settings.reused_seed``): written again with this seed
            (``dswm.protocol.reuse.reuse_evaluation``, which checks first that it is this job's evaluation), the
            MLflow run tagged ``reused_from`` with its days.parquet; None: the job evaluates.

    A learning method loads ``model``, the model of its training source, and ``manifest``, that source's
    training manifest. days.parquet records the model (``dswm.pipeline.setup.model_record``) and the method's
    resolved settings with the BCD search it runs (``setup.method_record``) in its metadata; the MLflow run is
    tagged ``train_source``, ``model_path`` and ``model_sha256``. ``record_out`` (``evaluation.write_eval_record``:
    the SHA-256 and size of days.parquet and trajectory.npz) is written last, once both are complete and logged; the
    audit (``protocol.result_records``) proves from it that neither changed since.
    """
    s = set_up(job, "evaluation", EvaluationSettings, intensity)
    limits = build(EvalDayLimits, s.job["eval_days"], "eval_days")
    tensor = load_tensor(tensor_dir)
    with open_run(s, mlflow_cfg=mlflow_cfg, stage="evaluate", dataset=dataset, method=method, seed=seed, repo=repo,
                  keep=[days_out, trajectory_out]) as run:
        result, record, settings_record = evaluate_controller(
            run, s, tensor=tensor, tensor_dir=tensor_dir, limits=limits, dataset=dataset, method=method, seed=seed,
            display=display, model=model, manifest=manifest, reuse=reuse)
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


def evaluate_controller(run: tracking.JobRun, s: JobSetup, *, tensor, tensor_dir: str | Path, limits: EvalDayLimits,
                        dataset: str, method: str, seed: int, display: Display, model: str | Path | None,
                        manifest: str | Path | None, what: str | None = None,
                        reuse: Mapping[str, str | Path] | None = None) -> tuple[evaluation.EvalResult, dict, dict]:
    """What every evaluate job does inside its run: record the demand tensor as the run's input, build the
    controller, load its training source's model (:func:`dswm.pipeline.setup.load_source_model`; ``what`` names
    the job in its error) and evaluate it on the days of ``limits`` (the slice's ``eval_days``); or, given
    ``reuse`` (see :func:`evaluate_job`), take that evaluation at this seed instead
    (:func:`dswm.protocol.reuse.reuse_evaluation`) and tag the run ``reused_from``.

    Returns:
        (the evaluation, the model record, the method record (:func:`dswm.pipeline.setup.method_record`)).
    """
    log_demand_input(run, tensor_dir, dataset, "evaluation")
    ctrl = build_controller(s, method, seed)
    day_limits = {"id": limits.id, "ood": limits.ood}
    if reuse:
        settings_record = method_record(s.method, ctrl)
        result, record = reuse_evaluation(reuse, tensor=tensor, controller=ctrl, scenario=s.scenario, seed=seed,
                                          limits=day_limits, profile=s.job["profile"], method_record=settings_record)
        run.set_tags({"reused_from": str(reuse["days"])})
        print(f"{dataset}/{method}/seed{seed}: the seed does not change this method's result; reused "
              f"{reuse['days']}", file=sys.stderr, flush=True)
        return result, record, settings_record
    record = load_source_model(run, ctrl, s.method, model=model, manifest=manifest, what=what)
    settings_record = method_record(s.method, ctrl)
    result = evaluation.evaluate(tensor=tensor, controller=ctrl, scenario=s.scenario, seed=seed, limits=day_limits,
                                 profile=s.job["profile"], device=s.settings.device, batch_days=s.settings.batch_days,
                                 progress_interval_s=display.progress_mininterval_s)
    return result, record, settings_record


def calibrate_job(*, job: Mapping[str, Any], tensor_dir: str | Path, out: str | Path) -> dict:
    """Bisection of the demand intensity (see dswm.protocol.calibration); writes and returns the JSON report.

    Args:
        job: the plain form of ``dswm.settings.calibrate_slice`` (the scenario less its demand intensity).
    """
    ev = build(Runtime, job["runtime"], "runtime")
    init_process(ev)
    cal = build(CalibrationSettings, job["calibration"], "calibration")
    # The value being calibrated is not an input: the bracket's lower end stands in until bisection sets it.
    scenario = Scenario.from_dict({**job["scenario"], "demand_intensity": cal.bracket[0]})
    tensor = load_tensor(tensor_dir)
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
    s = set_up(job, "evaluation", EvaluationSettings, intensity)
    ev, scenario, m = s.settings, s.scenario, s.method
    sel = build(SelectionSettings, job["selection"], "selection")
    tensor = load_tensor(tensor_dir)
    fit_days, val_days = selection.split_training_days(tensor, sel.fit_days)
    score_kw = {"tensor": tensor, "scenario": scenario, "days": val_days, "seed": 0, "device": ev.device,
                "batch_days": ev.batch_days, "progress_interval_s": display.progress_mininterval_s}
    greedy = registry.BUILTIN["greedy"].target
    search = selection.select_search(
        make=lambda cand: registry.build("greedy", target=greedy, options=cand, seed=0, device=ev.device),
        candidates=sel.search_candidates, budget_ms=sel.search_budget_ms, **score_kw)
    torch.manual_seed(0)
    ctrl = build_controller(s, m.name, 0)
    planner = selection.select_planner(controller=ctrl, fit_days=fit_days, gammas=sel.gamma, sigma0s=sel.sigma0,
                                       run_dir=run_dir, **score_kw)
    report = {"dataset": tensor.meta["dataset"], "profile": job["profile"], "torch_threads": ev.torch_threads,
              "validation_days": [tensor.labels[d] for d in val_days], "search": search, "planner": planner}
    write_json(out, report)
    return report
