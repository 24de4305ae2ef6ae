"""Calibration of the demand intensity u (docs/PROTOCOL.md §2).

With the published constants alone every cell would be fully served, so the requested rate of a cell is
x_g * u * r0 with ONE u for every dataset, chosen so that Static serves ``target`` (0.74) on the Milan
TRAINING days. Static's fleet does not depend on u (it holds the K-means spots), and a larger u asks more of
the same links, so the served ratio falls monotonically in u and a bisection (in log u) finds it.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from dswm.methods.classical import StaticController
from dswm.config import ConfigError
from dswm.sim.scenario import Scenario
from dswm.methods.base import DayContext
from dswm.sim.core import core_from_tensor


def static_score(tensor, scenario: Scenario, days: np.ndarray, *, device: str = "cpu") -> float:
    """Mean over ``days`` of Static's day score (mean of the day's T served ratios).

    Args:
        tensor: a prep.tensor.DemandTensor.
        scenario: constants (with the demand intensity to score).
        days: tensor day indices.
        device: torch device of the environment.
    """
    core = core_from_tensor(tensor, scenario, days, device=device)
    grid, labels, init_pos = core.grid, tensor.labels, core.init_pos.cpu().numpy()
    ctrl = StaticController(name="static")
    ctxs = [DayContext(dataset=tensor.meta["dataset"], day=int(d), label=labels[d], split="train", grid=grid,
                       scenario=scenario, geometry=grid.geometry(), cells=grid.cells(), init_pos=init_pos,
                       device=device) for d in days]
    obs = core.reset(list(range(len(days))))
    ctrl.reset_batch(ctxs)
    srs = [core.sr0]
    for _ in range(scenario.slots_per_day - 1):
        out = core.step(ctrl.act_batch(obs))
        obs = out.obs
        srs.append(out.sr)
    return float(np.stack(srs, 1).mean(1).mean())


def calibrate(*, tensor, scenario: Scenario, target: float, bracket: tuple[float, float], tolerance: float,
              max_iter: int, device: str = "cpu") -> dict:
    """Find u with Static's mean served ratio on the TRAINING days of ``tensor`` equal to ``target``.

    Args:
        tensor: the calibration dataset's DemandTensor (Milan).
        scenario: constants; its demand_intensity is replaced by the candidates.
        target: served ratio to reach.
        bracket: (low, high) values of u with score(low) >= target >= score(high).
        tolerance: stop once |score - target| <= tolerance.
        max_iter: bisection steps at most.
        device: torch device.

    Returns:
        {"demand_intensity", "served_ratio", "target", "iterations", "dataset", "data_source", "train_days"}.
    Raises:
        ConfigError: the bracket does not hold the target, or ``max_iter`` steps do not reach the tolerance.
    """
    days = np.asarray(tensor.train_days, dtype=np.int64)

    def score(u: float) -> float:
        return static_score(tensor, dataclasses.replace(scenario, demand_intensity=u), days, device=device)

    lo, hi = float(bracket[0]), float(bracket[1])
    s_lo, s_hi = score(lo), score(hi)
    if not (s_lo >= target >= s_hi):
        raise ConfigError(f"config.yaml: key 'calibration.bracket' = [{lo}, {hi}] does not bracket the target "
                          f"{target}: Static serves {s_lo:.4f} at u={lo} and {s_hi:.4f} at u={hi} (expected the "
                          f"first >= target >= the second)")
    u, s = (lo, s_lo) if abs(s_lo - target) <= abs(s_hi - target) else (hi, s_hi)
    it = 0
    while abs(s - target) > tolerance and it < max_iter:
        it += 1
        u = math.sqrt(lo * hi)  # bisection in log u: the bracket spans orders of magnitude
        s = score(u)
        if s > target:
            lo = u
        else:
            hi = u
    if abs(s - target) > tolerance:
        raise ConfigError(f"config.yaml: keys 'calibration.max_iter' = {max_iter} and 'calibration.tolerance' = "
                          f"{tolerance:g}: after {it} bisection steps Static serves {s:.6f} at u={u:.6g}, still "
                          f"{abs(s - target):.2e} from the target {target} (raise max_iter or the tolerance)")
    labels = tensor.labels
    return {"demand_intensity": u, "served_ratio": s, "target": target, "iterations": it,
            "dataset": tensor.meta["dataset"], "data_source": tensor.meta["source"],
            "train_days": [labels[d] for d in days]}
