"""DSWM+ where the room is (workflow/rules/room_fill.smk): the candidate's fit on training days and the evaluations
of figure ``room_fill`` (config.yaml ``figures.room_fill``), in one regime of the headroom map.

* :func:`room_fill_fit_job`       the candidate's anchoring per imagined step rho_k and its gamma, chosen on TRAINING
                                  days only, written as JSON: DSWM+ (the world model trained in the regime) replays the
                                  ``fit_days`` training days before the last ``validation_days``; rho_k is the least-
                                  squares anchoring of its open-loop maps (``dswm.methods.dswm.quality``); then DSWM+
                                  with those rho_k plans the validation days once per gamma of ``gammas``.
* :func:`room_fill_evaluate_job`  one arm's evaluation on the test days (``dswm.pipeline.extra.extra_evaluate_job``),
                                  the candidate with the fit's rho_k and gamma in its planner.

Nothing here enters a table; the runs are logged in the figures' experiment like the other extra runs.
"""
from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from dswm.config import build
from dswm.methods.dswm import quality
from dswm.pipeline.extra import extra_evaluate_job, variant_run
from dswm.pipeline.setup import build_controller, load_source_model, load_tensor, log_demand_input, set_up
from dswm.protocol.replay import replay
from dswm.protocol.selection import score_days
from dswm.settings import Display, EvaluationSettings, RoomFillSettings
from prep.atomic import write_json


def training_split(tensor, fit_days: int, validation_days: int) -> tuple[list[int], list[int]]:
    """(fit days, validation days) of the tensor's TRAINING days in time order: the last ``validation_days`` validate
    (held out as ``select`` holds them out), the ``fit_days`` before them fit rho_k.

    Raises:
        ValueError: fewer than ``fit_days + validation_days`` training days.
    """
    train = [int(d) for d in tensor.train_days]
    need = fit_days + validation_days
    if len(train) < need:
        raise ValueError(f"meta.json of {tensor.meta['dataset']}: {len(train)} training day(s), but "
                         f"figures.room_fill.fit_days + validation_days = {need} need as many")
    return train[len(train) - need: len(train) - validation_days], train[len(train) - validation_days:]


def with_fit(job: Mapping[str, Any], fit: Mapping[str, Any]) -> dict:
    """The plain evaluate slice ``job`` with the fit's rho_k and gamma in its method's planner."""
    planner = {**job["method"]["options"]["planner"], "rho_steps": [float(r) for r in fit["rho_steps"]],
               "gamma": float(fit["gamma"])}
    options = {**job["method"]["options"], "planner": planner}
    return {**job, "method": {**job["method"], "options": options}}


def room_fill_fit_job(*, job: Mapping[str, Any], mlflow_cfg: Mapping[str, Any], display: Display,
                      tensor_dir: str | Path, dataset: str, variant: str, seed: int, model: str | Path,
                      manifest: str | Path, out: str | Path, repo: str | Path,
                      intensity: str | Path | None = None) -> dict:
    """Fit the candidate's rho_k and choose its gamma on training days (module docstring); write ``out``.

    Args:
        job: the plain ``dswm.settings.room_fill_slice`` of the candidate (DSWM+ in the regime, ``room_fill``).
        variant: the regime's variant name (an MLflow tag); model, manifest: the world model trained in the regime.
        intensity: the calibrate rule's record, when ``scenario.demand_intensity`` is ``calibrate``.

    Returns:
        The record written: the days, rho_k, the forecast RMSE per step (fixed rho, rho_k, model, persistence), the
        validation served ratio of every gamma and the chosen one.
    """
    s = set_up(job, "evaluation", EvaluationSettings, intensity)
    rf = build(RoomFillSettings, job["room_fill"], "figures.room_fill")
    tensor = load_tensor(tensor_dir)
    fit_days, val_days = training_split(tensor, rf.fit_days, rf.validation_days)
    with variant_run(s, mlflow_cfg=mlflow_cfg, part="room_fill_fit", variant=variant, dataset=dataset,
                     method=s.method.name, seed=seed, repo=repo, keep=[out]) as run:
        run.set_tags({"stage": "extra", "variant": variant, "extra_job": "room_fill_fit"})
        log_demand_input(run, tensor_dir, dataset, "room_fill_fit")
        ctrl = build_controller(s, s.method.name, seed)
        record = load_source_model(run, ctrl, s.method, model=model, manifest=manifest, what="room_fill_fit")
        base = ctrl.options
        horizon = base.planner.horizon
        print(f"room_fill_fit: replaying {len(fit_days)} training day(s)", file=sys.stderr)
        plays, _ = replay(tensor=tensor, controller=ctrl, scenario=s.scenario, seed=seed, days={"train": fit_days},
                          profile=job["profile"], device=s.settings.device,
                          progress_interval_s=display.progress_mininterval_s)
        moments = None
        for play in plays:
            posts = quality.posteriors(ctrl.model, play)
            starts = np.arange(0, len(play.actions) - horizon + 1)
            pred = quality.open_loop_maps(ctrl.model, posts, play.actions, starts, horizon)
            moments = quality.add_moments(moments, quality.anchor_moments(
                pred, play.demand.reshape(play.demand.shape[0], -1), starts))
        rho = quality.fit_rho_steps(moments)
        rmse = {name: np.sqrt(quality.anchored_mse(moments, r)).tolist()
                for name, r in (("rho_fixed", base.planner.rho), ("rho_k", rho), ("model", 0.0),
                                ("persistence", 1.0))}
        rows = []
        for g in rf.gammas:
            planner = dataclasses.replace(base.planner, rho_steps=tuple(float(r) for r in rho), gamma=float(g))
            ctrl.options = dataclasses.replace(base, planner=planner)
            print(f"room_fill_fit: gamma={g} on {len(val_days)} validation day(s)", file=sys.stderr)
            rows.append({"gamma": float(g), **score_days(tensor=tensor, controller=ctrl, scenario=s.scenario,
                                                         days=val_days, seed=seed, device=s.settings.device,
                                                         batch_days=s.settings.batch_days,
                                                         progress_interval_s=display.progress_mininterval_s)})
        ctrl.options = base
        best = max(rows, key=lambda r: r["sr_mean"])  # ties: the first in config order
        out_record = {"dataset": dataset, "variant": variant, "seed": seed, "method": s.method.name,
                      "fit_days": [tensor.labels[d] for d in fit_days],
                      "validation_days": [tensor.labels[d] for d in val_days], "read_test_data": False,
                      "rho_fixed": float(base.planner.rho), "rho_steps": [float(r) for r in rho],
                      "rmse_per_step": rmse, "gamma_candidates": rows, "gamma": best["gamma"], "model": record}
        for k, r in enumerate(rho, 1):
            run.log_metrics({"room_fill/rho_k": float(r), "room_fill/rmse_rho_k": rmse["rho_k"][k - 1],
                             "room_fill/rmse_rho_fixed": rmse["rho_fixed"][k - 1]}, step=k)
        run.log_metrics({"room_fill/gamma": best["gamma"], "room_fill/validation_sr": best["sr_mean"]})
        write_json(out, out_record)
        run.log_artifact(out)
    return out_record


def room_fill_evaluate_job(*, job: Mapping[str, Any], fit: str | Path | None = None, **kw) -> Any:
    """One arm of figure ``room_fill`` on the test days: :func:`dswm.pipeline.extra.extra_evaluate_job` of ``job``
    (a ``dswm.settings.room_fill_slice``), with the rho_k and gamma of the fit record ``fit`` in the planner when
    given (the candidate)."""
    if fit is not None:
        record = json.loads(Path(fit).read_text())
        missing = [k for k in ("rho_steps", "gamma") if k not in record]
        if missing:
            raise ValueError(f"{fit}: no {', '.join(missing)} (expected the room_fill_fit job's record)")
        job = with_fit({k: v for k, v in job.items() if k != "room_fill"}, record)
    return extra_evaluate_job(job=job, **kw)
