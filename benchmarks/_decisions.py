"""Per-decision timing of the planners on a prepared tensor: the code ``bench_methods.py`` and
``bench_learners.py`` share.

* :func:`scenario_for`: the configured scenario, u from a calibrate record when the config calibrates.
* :func:`planning_controller`: a method's controller from resolved settings (untrained weights for a learner).
* :func:`time_decisions`: per-decision milliseconds of one controller over consecutive slots of one day.
"""
from __future__ import annotations

import dataclasses
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from dswm import settings as runconfig
from dswm.methods.base import DayContext
from dswm.sim.core import core_from_tensor
from dswm.sim.scenario import DEMO_INTENSITY


def scenario_for(settings: runconfig.Settings, record: Path, root: Path | None = None):
    """(scenario, where u came from): u from ``record`` (the calibrate rule's output) when the config calibrates and
    the record exists, else the demo's stand-in; a fixed u from the config as is."""
    if settings.scenario.calibrates:
        if record.is_file():
            where = str(record.relative_to(root)) if root is not None and record.is_relative_to(root) else str(record)
            return runconfig.calibrated_scenario(settings.scenario, record), where
        return dataclasses.replace(settings.scenario, demand_intensity=DEMO_INTENSITY), "DEMO_INTENSITY stand-in"
    return settings.scenario, "config.yaml"


def planning_controller(settings: runconfig.Settings, method: str, core, **options):
    """``method``'s controller under ``settings`` with ``options`` changed; a learning method gets untrained
    weights (planning costs the same) and its normalizer from the core's first day."""
    m = settings.methods[method]
    opts = dataclasses.replace(m.options, **options) if options else m.options
    ctl = m.controller_class(name=method, seed=0, device="cpu", options=opts)
    if m.learns:
        ctl.model = ctl._build_model(core.grid, core.scenario)
        ctl.model.set_normalizer(torch.as_tensor(core.demand[:1].cpu().numpy()))
        ctl.model.eval()
    return ctl


def time_decisions(ctl, tensor, scenario, day: int, start: int, slots: int) -> dict:
    """Median, p90 and spread of per-decision ms over ``slots`` decisions from slot ``start`` of tensor day ``day``
    (batch of one day); the first decided slot (one-time allocations, compiling) is reported apart.

    The fleet holds its initial deployment until ``start``, then the controller steps the day with its own
    actions.
    """
    core = core_from_tensor(tensor, scenario, [day])
    grid = core.grid
    ctx = DayContext(dataset=tensor.meta["dataset"], day=day, label=tensor.labels[day], split="id", grid=grid,
                     scenario=scenario, geometry=grid.geometry(), cells=grid.cells(), init_pos=core.init_pos.numpy(),
                     device="cpu", demand=tensor.demand[day] if ctl.clairvoyant else None)
    obs = core.reset([0])
    if ctl.batched:
        ctl.reset_batch([ctx])
    else:
        ctl.reset(ctx)
    hold = np.zeros((1, scenario.n_uavs, 3), dtype=np.float32)
    for _ in range(start):
        obs = core.step(hold).obs
    times, served = [], []
    for _ in range(slots + 1):
        t0 = time.perf_counter()
        action = ctl.act_batch(obs) if ctl.batched else ctl.act({k: v[0] for k, v in obs.items()})[None]
        times.append(1e3 * (time.perf_counter() - t0))
        out = core.step(action)
        obs = out.obs
        served.append(float(np.asarray(out.sr).mean()))
    first, times = times[0], times[1:]
    out = {"median_ms": round(statistics.median(times), 1), "p90_ms": round(float(np.percentile(times, 90)), 1),
           "min_ms": round(min(times), 1), "max_ms": round(max(times), 1), "first_slot_ms": round(first, 1),
           "decisions": len(times), "served_ratio_mean": round(statistics.mean(served), 4)}
    if hasattr(ctl, "day_stats"):
        stats = ctl.day_stats()
        if stats and stats[0]:
            out["day_stats"] = {k: round(v, 2) for k, v in stats[0].items()}
    return out


def first_test_day(tensor) -> int:
    """The tensor index of the first test day."""
    return next(d["index"] for d in tensor.meta["days"] if d["split"] == "test")
