"""Statistics family, part 2: what is derived from the training days besides the normalizer.

* `check_week`: YJMob's recovered week (period and pseudo-weekend phases, which pick the eval days) equals a
  recomputation from the raw TRAINING daily totals.
* `check_initial_positions`: the initial (and static) UAV positions recorded with every result are the
  demand-weighted K-means of the TRAINING mean map, and differ from the all-days K-means.
* `check_calibration`: the demand intensity u the jobs used (config.yaml's number, or with
  `scenario.demand_intensity: calibrate` the calibrate rule's record) reproduces the calibration target with
  Static on the reference dataset's TRAINING days, and the calibration record names those days only.
"""
from __future__ import annotations

import numpy as np

from audits.context import AuditContext, AuditInputError
from audits.positions import recorded_initial_positions
from audits.report import Check
from audits.statistics import recompute

POS_ATOL_M = 1.0
"""Recorded and recomputed K-means positions agree within 1 m (float32 metres on km-sized areas)."""
FIXED_POINT_M = 0.5
"""K-means from another start may land on another optimum of the same map: then one weighted Lloyd step on
the training map moves no centre more than this (scikit-learn converges to ~1e-4 m on these grids)."""
SR_TOL = 0.005
"""|Static served ratio at the configured u - target| on the training days (u is stored rounded)."""


def recover_week(day_numbers: np.ndarray, totals: np.ndarray, *, min_lag: int, max_lag: int,
                 n_weekend: int) -> tuple[int, list[int]]:
    """Independent recomputation of the week: peak autocorrelation lag, lowest-mean phases.

    Args:
        day_numbers: (n,) day numbers of the training days; totals: (n,) their daily totals.
    Returns:
        (lag, sorted pseudo-weekend phases).
    """
    y = totals - totals.mean()
    den = float(y @ y)
    hi = min(max_lag, len(y) // 2)
    acf = {k: (float(y[:-k] @ y[k:]) / den if den > 0 else 0.0) for k in range(min_lag, hi + 1)}
    lag = max(acf, key=lambda k: (acf[k], -k))
    phase = day_numbers % lag
    means = np.array([totals[phase == p].mean() for p in range(lag)])
    return lag, sorted(int(p) for p in np.argsort(means, kind="stable")[:n_weekend])


def check_week(ctx: AuditContext) -> Check:
    """The recovered week of numbered-day datasets comes from the training days."""
    chk = Check(id="statistics.week", family="statistics",
                claim="The recovered week (period, pseudo-weekend phases) of numbered-day datasets equals the "
                      "recomputation from the raw TRAINING daily totals (it picks YJMob's eval days).")
    for ds in ctx.datasets:
        try:
            meta = ctx.meta(ds)
            if not meta.get("week"):
                chk.evidence[ds] = "calendar dates: weekends from the date, nothing recovered"
                continue
            r = recompute(ctx, ds)
        except AuditInputError as exc:
            chk.fail(f"{exc} — the week cannot be verified")
            continue
        wcfg = ctx.section(ds).week
        nums = np.array([int(meta["days"][i]["label"][1:]) for i in r.train])
        totals = r.values[r.train].sum(axis=(1, 2, 3))
        lag, phases = recover_week(nums, totals, min_lag=wcfg.min_lag, max_lag=wcfg.max_lag,
                                   n_weekend=wcfg.n_weekend_phases)
        all_nums = np.array([int(d["label"][1:]) for d in meta["days"]])
        lag_all, phases_all = recover_week(all_nums, r.values.sum(axis=(1, 2, 3)), min_lag=wcfg.min_lag,
                                           max_lag=wcfg.max_lag, n_weekend=wcfg.n_weekend_phases)
        stored = meta["week"]
        got = (int(stored.get("lag", -1)), sorted(int(p) for p in stored.get("pseudo_weekend_phases", [])))
        if got != (lag, phases):
            leak = (" — it equals the all-days recovery: week recovered from all days"
                    if got == (lag_all, phases_all) and (lag_all, phases_all) != (lag, phases) else "")
            chk.fail(f"{ctx.rel(ctx.meta_path(ds))}: week lag {got[0]}, pseudo-weekend phases {got[1]}; the raw "
                     f"training daily totals give lag {lag}, phases {phases}{leak}")
        flags = [(all_nums[i] % lag) in set(phases) for i in range(len(all_nums))]
        wrong = [d["label"] for d, f in zip(meta["days"], flags) if bool(d.get("weekend")) != f]
        if wrong:
            chk.fail(f"{ctx.rel(ctx.meta_path(ds))}: weekend labels of {wrong[:5]} disagree with the recovered week")
        chk.evidence[ds] = {"stored": {"lag": got[0], "phases": got[1]}, "train": {"lag": lag, "phases": phases},
                            "all_days": {"lag": lag_all, "phases": phases_all}}
    return chk


def _grid_and_map(ctx: AuditContext, ds: str, days: np.ndarray):
    from dswm.sim.core import grid_of

    t = ctx.tensor(ds)
    grid = grid_of(t)
    return grid, t.demand[days].astype(np.float64).mean(axis=(0, 1))


def kmeans_positions(ctx: AuditContext, ds: str, days: np.ndarray) -> np.ndarray:
    """(K, 2) demand-weighted K-means (dswm.sim.core.initial_positions) of the mean map over `days`."""
    from dswm.sim.core import initial_positions

    grid, mean_map = _grid_and_map(ctx, ds, days)
    return initial_positions(mean_map, grid, ctx.scenario.n_uavs, ctx.scenario.init.kmeans_seed)


def lloyd_residual(pos: np.ndarray, cells: np.ndarray, weights: np.ndarray) -> float:
    """Largest move (m) of one weighted Lloyd step from `pos`: 0 at a weighted K-means fixed point.

    Args:
        pos: (K, 2) centres; cells: (G, 2) cell centres; weights: (G,) demand weights.
    """
    d2 = ((cells[:, None, :] - pos[None]) ** 2).sum(-1)
    assign = d2.argmin(1)
    moved = pos.astype(np.float64).copy()
    for k in range(len(pos)):
        m = assign == k
        if weights[m].sum() > 0:
            moved[k] = (cells[m] * weights[m, None]).sum(0) / weights[m].sum()
    return float(np.abs(moved - pos).max())


def check_initial_positions(ctx: AuditContext) -> Check:
    """Recorded initial (static) positions = K-means of the training mean map, not of all days."""
    chk = Check(id="statistics.initial_positions", family="statistics",
                tolerance=f"{POS_ATOL_M:g} m per coordinate against the recomputed K-means, or a weighted Lloyd "
                          f"step on the training map moving no centre more than {FIXED_POINT_M:g} m (another "
                          f"K-means optimum of the same training map)",
                claim="The initial (and Static) UAV positions recorded with every result are the demand-weighted "
                      "K-means of the TRAINING mean demand map (recomputed, or a K-means fixed point of it); "
                      "where the all-days map gives other centres, they are not those.")
    for ds in ctx.datasets:
        try:
            train_pos = kmeans_positions(ctx, ds, ctx.train_index(ds))
            grid, w_train = _grid_and_map(ctx, ds, ctx.train_index(ds))
            _, w_all = _grid_and_map(ctx, ds, np.arange(len(ctx.meta(ds)["days"])))
            recorded = recorded_initial_positions(ctx, ds)
        except AuditInputError as exc:
            chk.fail(f"{exc} — the initial positions cannot be verified")
            continue
        cells = grid.cells().numpy().astype(np.float64)
        w_train, w_all = w_train.ravel(), w_all.ravel()
        ev = {"files": len(recorded), "match_recomputed": 0, "max_residual_train_m": 0.0,
              "all_days_residual_of_train_kmeans_m": lloyd_residual(train_pos, cells, w_all),
              "train_kmeans": np.round(train_pos, 1)}
        for where, pos in recorded.items():
            if pos.shape != train_pos.shape:
                chk.fail(f"{where}: {pos.shape} positions, expected {train_pos.shape}")
                continue
            match = float(np.abs(pos - train_pos).max()) <= POS_ATOL_M
            r_train, r_all = lloyd_residual(pos, cells, w_train), lloyd_residual(pos, cells, w_all)
            ev["match_recomputed"] += int(match)
            ev["max_residual_train_m"] = max(ev["max_residual_train_m"], r_train)
            if not match and r_train > FIXED_POINT_M:
                leak = (" — they are a K-means solution of the ALL-DAYS mean map: positions computed on all days"
                        if r_all <= FIXED_POINT_M else "")
                chk.fail(f"{where}: initial positions are not the K-means of the training mean map (a Lloyd step "
                         f"on it moves a centre {r_train:.1f} m; recomputed K-means differs by "
                         f"{float(np.abs(pos - train_pos).max()):.1f} m){leak}")
        chk.evidence[ds] = ev
    return chk


def static_served_ratio(ctx: AuditContext, ds: str, days: np.ndarray, intensity: float) -> float:
    """Mean served ratio of Static (K-means positions held all day) over `days` at demand intensity u."""
    import dataclasses

    from dswm.methods.classical import StaticController
    from dswm.methods.base import DayContext
    from dswm.sim.core import FleetCore, grid_of

    t = ctx.tensor(ds)
    scenario = dataclasses.replace(ctx.scenario, demand_intensity=float(intensity))
    grid = grid_of(t)
    # The initial deployment is derived again from the training days that config names, not from meta.json.
    init = kmeans_positions(ctx, ds, ctx.train_index(ds))
    labels = t.labels
    core = FleetCore(demand=t.demand, grid=grid, scenario=scenario, init_pos=init, dataset=ds, day_labels=labels)
    ctl = StaticController(name="static")
    obs = core.reset(list(days))
    ctl.reset_batch([DayContext(dataset=ds, day=int(d), label=labels[d], split="train", grid=grid, scenario=scenario,
                                geometry=core.geom, cells=core.cells, init_pos=init) for d in days])
    srs = [core.sr0]
    for _ in range(scenario.slots_per_day - 1):
        out = core.step(ctl.act_batch(obs))
        obs = out.obs
        srs.append(out.sr)
    return float(np.mean(np.stack(srs, 1)))


def check_calibration(ctx: AuditContext) -> Check:
    """The intensity u the jobs used was calibrated on the reference dataset's training days."""
    from audits.positions import calibration_record

    cal = ctx.settings.calibration
    ds, target = cal.dataset, float(cal.target_served_ratio)
    from_record = ctx.intensity_calibrated  # scenario.demand_intensity: calibrate, u is the record's
    source = (f"the calibrate rule's record {ctx.rel(ctx.calibration_record_path)}" if from_record else
              "config.yaml's scenario.demand_intensity")
    chk = Check(id="statistics.calibration", family="statistics",
                tolerance=f"|served ratio - target| <= {SR_TOL:g}",
                claim=f"Static at the demand intensity u the jobs used ({source}) serves the calibration target on "
                      f"the {ds} TRAINING days (recomputed), and the calibration record names those days only.")
    try:
        u = float(ctx.scenario.demand_intensity)
        train = ctx.train_index(ds)
        sr_train = static_served_ratio(ctx, ds, train, u)
    except (AuditInputError, KeyError) as exc:
        chk.fail(f"{exc} — the calibration cannot be verified")
        return chk
    chk.evidence = {"dataset": ds, "u": u, "u_from": source, "target": target, "static_sr_train": sr_train}
    if not abs(sr_train - target) <= SR_TOL:
        sr_test = static_served_ratio(ctx, ds, ctx.test_index(ds), u)  # only to name the leak
        chk.evidence["static_sr_test"] = sr_test
        leak = (" — it matches the TEST days instead: u calibrated on test days"
                if abs(sr_test - target) <= SR_TOL else "")
        fix = ("the record does not reproduce its own calibration; run the calibrate rule again" if from_record else
               "run the calibrate rule and copy its value, or set it to calibrate")
        where = (f"{ctx.rel(ctx.calibration_record_path)}: demand_intensity" if from_record else
                 "config.yaml: scenario.demand_intensity")
        chk.fail(f"{where} = {u:g} gives Static a served ratio of {sr_train:.4f} on the {ds} training days, target "
                 f"{target:g}{leak} ({fix})")
    try:
        where, rec = calibration_record(ctx)
    except FileNotFoundError as exc:
        if from_record:  # not reached in practice: ctx.scenario already needed the record
            chk.fail(f"{exc} — scenario.demand_intensity is calibrate, so u must come from it")
        else:
            chk.evidence["record"] = f"{exc}; u verified by the recomputation above only"
        return chk
    except AuditInputError as exc:
        chk.fail(str(exc))
        return chk
    labels = [d["label"] for d in ctx.meta(ds)["days"]]
    want = [labels[i] for i in train]
    chk.evidence["record"] = {"file": where, "demand_intensity": rec.get("demand_intensity"),
                              "served_ratio": rec.get("served_ratio"), "days": len(rec.get("train_days", []))}
    if rec.get("dataset") != ds:
        chk.fail(f"{where}: calibrated on dataset {rec.get('dataset')!r}, config calibration.dataset is {ds!r}")
    got = list(rec.get("train_days", []))
    if got != want:
        extra = [d for d in got if d not in want]
        chk.fail(f"{where}: calibrated on days {got}; expected the {ds} training days {want[0]}..{want[-1]}"
                 + (f" — it used non-training day(s) {extra}" if extra else ""))
    if rec.get("data_source") != ctx.meta(ds).get("source"):
        chk.fail(f"{where}: calibrated on {rec.get('data_source')!r} data, the prepared {ds} data is "
                 f"{ctx.meta(ds).get('source')!r}")
    return chk
