"""The world-model quality job (workflow/rules/wm.smk): one DSWM model, replayed on the main evaluation's days.

* :func:`wm_quality_job`  load the model of one (dataset, seed), replay its evaluation on the days the main
                          ``days.parquet`` holds (cut to ``figures.eval_days``), and write
                          ``results/extra/<dataset>/wm_quality/seed<seed>/``: ``rmse.parquet`` (demand error per day
                          and imagined step), ``returns.parquet`` (imagined and realized return per day),
                          ``maps.npz`` (the one-step maps of the first day) and ``record.json`` (written last: the
                          SHA-256 and size of the three, the model loaded and the replay check). One MLflow run,
                          stage "wm". Nothing here enters a table.

The computation is ``dswm.methods.dswm.quality``.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

import numpy as np
import polars as pl

from dswm.config import build, to_plain
from dswm.methods.dswm import quality
from dswm.pipeline.setup import build_controller, load_source_model, load_tensor, open_run, set_up
from dswm.protocol.replay import replay
from dswm.settings import Display, EvalDayLimits, EvaluationSettings
from dswm.sim.core import grid_of
from prep.atomic import atomic_path, save_npz, write_json
from prep.rawio import sha256_file

STAGE = "wm"
"""The MLflow ``stage`` tag of the job's run."""
REPLAY_TOLERANCE = 1e-6
"""Largest difference between a replayed day's score and the main evaluation's that counts as the same play."""
RMSE_COLUMNS = ("dataset", "seed", "day", "label", "split", "step", "starts", "mse_model", "mse_anchored",
                "mse_persistence", "mbps_per_unit")
RETURN_COLUMNS = ("dataset", "seed", "day", "label", "split", "decisions", "imagined_sr", "imagined_reward",
                  "realized_sr", "sr_mean_replay", "sr_mean_main")


def days_to_replay(days: pl.DataFrame, limits: EvalDayLimits, where: str) -> dict[str, list[int]]:
    """{split: tensor days} of a main ``days.parquet`` in its order, each split cut to ``limits`` (None: all its
    days, 0: none).

    Raises:
        ValueError: no day is left.
    """
    out: dict[str, list[int]] = {}
    for split in ("id", "ood"):
        listed = [int(d) for d in days.filter(pl.col("split") == split)["day"]]
        limit = getattr(limits, split)
        kept = listed if limit is None else listed[:limit]
        if kept:
            out[split] = kept
    if not out:
        raise ValueError(f"{where}: no evaluated day left after figures.eval_days {to_plain(limits)}; expected at "
                         f"least one day to replay")
    return out


def _write_parquet(frame: pl.DataFrame, path: str | Path) -> None:
    with atomic_path(path) as tmp:
        frame.write_parquet(tmp)


def wm_quality_job(*, job: Mapping[str, Any], mlflow_cfg: Mapping[str, Any], display: Display,
                   tensor_dir: str | Path, dataset: str, seed: int, model: str | Path, manifest: str | Path,
                   main_days: str | Path, rmse_out: str | Path, returns_out: str | Path, maps_out: str | Path,
                   record_out: str | Path, repo: str | Path, intensity: str | Path | None = None) -> dict:
    """Replay one DSWM model on the main evaluation's days and measure its world model (module docstring).

    Args:
        job: the plain ``dswm.settings.evaluate_slice`` of the method (``job["method"]``) plus ``wm_quality``
            (``figures.wm_quality``) and ``replay_days`` (``figures.eval_days``).
        mlflow_cfg: the ``mlflow`` section (``dswm.settings.tracking``): where the run is logged.
        model, manifest: the method's training source's model file and train_manifest.json.
        main_days: the main evaluation's days.parquet of (dataset, method, seed): the days replayed, and the scores
            the replay is checked against.
        intensity: the calibrate rule's record, when ``scenario.demand_intensity`` is ``calibrate``.

    Returns:
        The record written to ``record_out``.

    Raises:
        ValueError: the model does not hash to its manifest's ``model_sha256``, or the method has no world model.
    """
    s = set_up(job, "evaluation", EvaluationSettings, intensity)
    ev, scenario, m, job = s.settings, s.scenario, s.method, s.job
    horizon = int(job["wm_quality"]["horizon"])
    main = pl.read_parquet(main_days)
    days = days_to_replay(main, build(EvalDayLimits, job["replay_days"], "figures.eval_days"), str(main_days))
    tensor = load_tensor(tensor_dir)
    with open_run(s, mlflow_cfg=mlflow_cfg, stage=STAGE, dataset=dataset, method=m.name, seed=seed, repo=repo,
                  keep=[rmse_out, returns_out, maps_out], kind="wm_quality") as run:
        ctrl = build_controller(s, m.name, seed)
        record = load_source_model(run, ctrl, m, model=model, manifest=manifest)
        if getattr(ctrl, "model", None) is None or ctrl.settings.planner is None:
            raise ValueError(f"{m.name}: no world model and planner to measure (expected a DSWM method)")
        run.set_tags({"data_source": tensor.meta["source"]})
        plays, result = replay(tensor=tensor, controller=ctrl, scenario=scenario, seed=seed, days=days,
                               profile=job["profile"], device=ev.device,
                               progress_interval_s=display.progress_mininterval_s)
        planner = ctrl.settings.planner
        grid = grid_of(tensor)
        mbps = scenario.intensity * scenario.r0_bps / 1e6  # requested rate of one normalized unit, Mbps
        main_sr = {int(r["day"]): float(r["sr_mean"]) for r in main.iter_rows(named=True)}
        replay_sr = {int(r["day"]): float(r["sr_mean"]) for r in result.days.iter_rows(named=True)}
        rmse_rows, return_rows, maps = [], [], None
        for play in plays:
            q = quality.day_quality(ctrl.model, play, grid=grid, scenario=scenario, horizon=horizon, rho=planner.rho,
                                    lambda_u=planner.lambda_u)
            ident = {"dataset": dataset, "seed": seed, "day": play.day, "label": play.label, "split": play.split}
            for k in range(horizon):
                rmse_rows.append({**ident, "step": k + 1, "starts": len(q["starts"]),
                                  **{c: float(q[c][k]) for c in ("mse_model", "mse_anchored", "mse_persistence")},
                                  "mbps_per_unit": mbps})
            return_rows.append({**ident, "decisions": len(play.actions), "imagined_sr": float(q["sr_hat"].mean()),
                                "imagined_reward": float(q["reward"].mean()), "realized_sr": float(q["sr"].mean()),
                                "sr_mean_replay": replay_sr[play.day], "sr_mean_main": main_sr[play.day]})
            if maps is None:
                maps = {"day": np.int64(play.day), "label": np.str_(play.label), "split": np.str_(play.split),
                        "seed": np.int64(seed), "true": play.demand.astype(np.float32), "one_step": q["one_step"],
                        "sr": play.sr.astype(np.float32)}
        rmse = pl.DataFrame(rmse_rows).select(RMSE_COLUMNS).with_columns(
            pl.col("seed", "day", "step", "starts").cast(pl.Int32))
        returns = pl.DataFrame(return_rows).select(RETURN_COLUMNS).with_columns(
            pl.col("seed", "day", "decisions").cast(pl.Int32))
        _write_parquet(rmse, rmse_out)
        _write_parquet(returns, returns_out)
        save_npz(maps_out, **maps)
        diff = float(max(abs(replay_sr[d] - main_sr[d]) for d in replay_sr))
        per_step = rmse.group_by("step").agg(pl.col("mse_model", "mse_anchored", "mse_persistence").mean()).sort("step")
        for row in per_step.iter_rows(named=True):
            run.log_metrics({f"wm/rmse_{c[4:]}": float(np.sqrt(row[c]))
                             for c in ("mse_model", "mse_anchored", "mse_persistence")}, step=row["step"])
        run.log_metrics({"wm/imagined_sr": float(returns["imagined_sr"].mean()),
                         "wm/realized_sr": float(returns["realized_sr"].mean()),
                         "wm/replay_max_abs_diff_sr_mean": diff})
        for path in (rmse_out, returns_out):
            run.log_artifact(path)
        out = {"files": {Path(p).name: {"sha256": sha256_file(Path(p)), "bytes": Path(p).stat().st_size}
                         for p in (rmse_out, returns_out, maps_out)},
               "model": record, "days": {s: [tensor.labels[d] for d in v] for s, v in days.items()},
               "horizon": horizon, "rho": planner.rho, "lambda_u": planner.lambda_u,
               "replay": {"max_abs_diff_sr_mean": diff, "tolerance": REPLAY_TOLERANCE,
                          "same_play": diff <= REPLAY_TOLERANCE, "main_days": str(main_days)}}
    write_json(record_out, out)
    return out
