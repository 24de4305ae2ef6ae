"""Checks every hand-written torch learner (MADDPG, GA-MATR, HRL-TPRA) must pass, on one toy core of 3 UAVs.

Each takes a ``make(seed, options)`` that builds the method's controller, so the method's test module states only
what is its own. The fixtures ``scenario3`` (the config scenario with 3 UAVs) and ``core`` (:func:`toy_core` on it)
are imported by those modules.
"""
from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np
import pytest
import torch

from dswm.methods.base import DayContext
from dswm.pipeline.setup import training_core
from dswm.protocol.evaluation import evaluate
from dswm.sim.core import FleetCore, Grid, initial_positions
from dswm.sim.env import synthetic_demand
from dswm.sim.fleet import ACTIVE
from prep.tensor import DemandTensor, GridSpec

GRID = Grid(rows=6, cols=6, cell_m=235.0)
DAY_IDS = np.array([2, 5, 7, 11])  # tensor days of the toy core's four training days


@pytest.fixture(scope="module")
def scenario3(scenario):
    return dataclasses.replace(scenario, n_uavs=3)


@pytest.fixture(scope="module")
def core(scenario3):
    return toy_core(scenario3)


def toy_core(scenario) -> FleetCore:
    """Four synthetic training days on a 6x6 grid, tensor days ``DAY_IDS`` (as ``training_core`` gives)."""
    demand = synthetic_demand(days=4, rows=GRID.rows, cols=GRID.cols, slots=scenario.slots_per_day, seed=3)
    c = FleetCore(demand=demand, grid=GRID, scenario=scenario,
                  init_pos=initial_positions(demand.mean(axis=(0, 1)), GRID, scenario.n_uavs, 0),
                  dataset="toy", day_labels=[f"2024-01-{d:02d}" for d in DAY_IDS])
    c.day_ids = DAY_IDS
    return c


def contexts(core, days) -> list[DayContext]:
    return [DayContext(dataset="toy", day=int(d), label=core.day_labels[d], split="train", grid=core.grid,
                       scenario=core.scenario, geometry=core.geom, cells=core.cells,
                       init_pos=core.init_pos.numpy()) for d in days]


def check_actions_bounded_and_moves_within_dmax(ctrl, core) -> float:
    """Two whole days: every action (2, K, 3) float32 in [-1, 1], every move within D_max; the largest move."""
    ctrl.reset_batch(contexts(core, [0, 3]))
    obs = core.reset([0, 3])
    d_max, moved = core.scenario.d_max_m, 0.0
    for _ in range(core.scenario.slots_per_day - 1):
        action = ctrl.act_batch(obs)
        assert action.shape == (2, core.scenario.n_uavs, 3) and action.dtype == np.float32
        assert np.all(np.abs(action) <= 1.0)
        pos, active = core.state.pos.clone(), core.state.status == ACTIVE
        obs = core.step(action).obs
        step = torch.linalg.norm(core.state.pos - pos, dim=-1)[active]
        if len(step):
            assert float(step.max()) <= d_max * (1 + 1e-5)
            moved = max(moved, float(step.max()))
    return moved


def check_same_seed_same_actions(make: Callable, options, core, tmp_path) -> None:
    """Two fits with seed 0 act identically, seed 1 differently; one day alone acts as in the batch."""
    obs = core.reset([1, 2])
    acts = []
    for seed, run in ((0, "a"), (0, "b"), (1, "c")):
        ctrl = make(seed, options)
        ctrl.fit(core, run_dir=tmp_path / run)
        ctrl.reset_batch(contexts(core, [1, 2]))
        acts.append(ctrl.act_batch(obs))
    assert np.array_equal(acts[0], acts[1])
    assert not np.allclose(acts[0], acts[2])
    ctrl.reset(contexts(core, [2])[0])
    single = ctrl.act({k: v[1] for k, v in obs.items()})
    np.testing.assert_allclose(single, acts[2][1], rtol=1e-5, atol=1e-6)


def check_save_load(ctrl, make: Callable, options, other_architecture, core, tmp_path, *, slots: int = 1) -> None:
    """The model file acts as the trained controller over ``slots`` slots; another architecture and another grid
    are refused."""
    ctrl.save(tmp_path / "model.pt")
    loaded = make(0, options)
    loaded.load(tmp_path / "model.pt")
    for c in (ctrl, loaded):
        c.reset_batch(contexts(core, [0]))
    obs = core.reset([0])
    for _ in range(slots):
        a = ctrl.act_batch(obs)
        np.testing.assert_array_equal(loaded.act_batch(obs), a)
        obs = core.step(a).obs
    with pytest.raises(ValueError, match="architecture"):
        make(0, other_architecture).load(tmp_path / "model.pt")
    other = dataclasses.replace(contexts(core, [0])[0], grid=Grid(rows=7, cols=6, cell_m=235.0))
    with pytest.raises(ValueError, match="6x6 grid"):
        loaded.reset_batch([other])


def check_trains_on_training_days_and_evaluates_batched_as_alone(make: Callable, options, scenario, tmp_path):
    """The train rule's core holds a tensor's training days only (the manifest says so); evaluating its test days
    batched or one by one gives the same scores."""
    demand = np.concatenate([synthetic_demand(days=5, rows=6, cols=6, seed=9)[:3] * 0.5,
                             synthetic_demand(days=2, rows=6, cols=6, seed=10) * 2.0])  # test days look different
    days = [{"index": i, "label": f"d{i}", "split": "train" if i in (0, 2, 4) else "test", "weekday": i % 7,
             "weekend": False} for i in range(5)]
    demand = demand[[0, 3, 1, 4, 2]]  # training days 0, 2, 4 (from the first draw), test days 1, 3
    meta = {"dataset": "toy", "source": "demo", "days": days, "slots_per_day": 144,
            "eval_days": {"id": [1], "ood": [3]}, "grid": {"rows": 6, "cols": 6, "cell_m": 235.0}}
    tensor = DemandTensor(demand=demand, meta=meta, grid=GridSpec(rows=6, cols=6, cell_m=235.0))
    train = training_core(tensor, scenario)
    assert train.n_days == 3
    torch.testing.assert_close(train.demand, torch.as_tensor(demand[[0, 2, 4]]).reshape(3, 144, 36))
    ctrl = make(0, options)
    manifest = ctrl.fit(train, run_dir=tmp_path)
    assert sorted(manifest["days"]) == [0, 2, 4] and manifest["day_labels"] == [f"d{d}" for d in manifest["days"]]
    runs = [evaluate(tensor=tensor, controller=ctrl, scenario=scenario, seed=0, limits={"id": None, "ood": None},
                     profile="smoke", device="cpu", batch_days=b, progress_interval_s=5.0).days for b in (True, False)]
    assert runs[0]["day"].to_list() == [1, 3]
    cols = ["sr_mean", "energy_kj_per_slot", "jain"]
    np.testing.assert_allclose(runs[0].select(cols).to_numpy(), runs[1].select(cols).to_numpy(), rtol=1e-5)
