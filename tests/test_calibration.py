"""Calibration of the demand intensity: the bisection lands on the target, recomputed with the physics alone.

(That every result of a run with `scenario.demand_intensity: calibrate` used the `calibrate` rule's value, and
that DEMO_INTENSITY is that value for the Milan demo data, is checked in test_integration.py, which prepares the
Milan tensor; reading the record: test_intensity.py.)
"""
import dataclasses

import numpy as np
import pytest
import torch

from dswm.protocol.calibration import calibrate, static_score
from dswm.config import ConfigError
from dswm.sim.core import grid_of, initial_deployment
from dswm.sim.physics import ServiceParams, served_ratio
from prep.tensor import DemandTensor, GridSpec


def tensor(n_train=2, n_test=1, rows=5, cols=5, seed=3):
    rng = np.random.default_rng(seed)
    n = n_train + n_test
    demand = rng.gamma(0.8, 1.0, size=(n, 144, rows, cols)).astype(np.float32)
    days = [{"index": i, "label": f"d{i}", "split": "train" if i < n_train else "test"} for i in range(n)]
    meta = {"dataset": "toy", "source": "demo", "days": days, "eval_days": {"id": [n_train], "ood": [n_train]}}
    return DemandTensor(demand=demand, meta=meta, grid=GridSpec(rows=rows, cols=cols, cell_m=235.0))


def fixed_fleet_score(t, scn, u):
    """Served ratio of a fleet that never moves (no battery can run out), from the physics alone."""
    grid = grid_of(t)
    pos = torch.tensor(initial_deployment(t, grid, scn))[None]
    params = ServiceParams.from_scenario(dataclasses.replace(scn, demand_intensity=u))
    x = torch.tensor(t.demand[t.train_days].reshape(-1, grid.n_cells))
    k = scn.n_uavs
    return float(served_ratio(x, pos.expand(len(x), k, 2), torch.ones(len(x), k, dtype=torch.bool), grid.cells(),
                              params=params).mean())


def test_bisection_finds_the_intensity_at_which_static_serves_the_target(make_scenario):
    scn = make_scenario(n_uavs=2, battery_j=1.0e12)
    t = tensor()
    rep = calibrate(tensor=t, scenario=scn, target=0.74, bracket=(1.0, 1000.0), tolerance=1e-4, max_iter=60)
    assert rep["served_ratio"] == pytest.approx(0.74, abs=1e-4)
    # the same number from the physics directly, with the fleet held at its K-means spots all day
    assert fixed_fleet_score(t, scn, rep["demand_intensity"]) == pytest.approx(0.74, abs=1e-4)
    assert rep["train_days"] == ["d0", "d1"] and rep["dataset"] == "toy"
    # the test day was never scored: changing it changes nothing
    t.demand[2] *= 10.0
    assert static_score(t, dataclasses.replace(scn, demand_intensity=rep["demand_intensity"]),
                        t.train_days) == pytest.approx(rep["served_ratio"], abs=1e-7)


def test_served_ratio_falls_with_the_intensity(make_scenario):
    scn = make_scenario(n_uavs=2, battery_j=1.0e12)
    t = tensor()
    scores = [fixed_fleet_score(t, scn, u) for u in (5.0, 50.0, 500.0)]
    assert scores[0] > scores[1] > scores[2]


def test_a_bracket_that_misses_the_target_names_the_key(make_scenario):
    scn = make_scenario(n_uavs=2, battery_j=1.0e12)
    with pytest.raises(ConfigError, match=r"calibration\.bracket"):
        calibrate(tensor=tensor(), scenario=scn, target=0.74, bracket=(1.0e4, 1.0e5), tolerance=1e-4, max_iter=10)


def test_a_bisection_that_does_not_reach_the_tolerance_is_an_error(make_scenario):
    scn = make_scenario(n_uavs=2, battery_j=1.0e12)
    with pytest.raises(ConfigError, match=r"'calibration\.max_iter' = 3 .* after 3 bisection steps"):
        calibrate(tensor=tensor(), scenario=scn, target=0.74, bracket=(1.0, 1000.0), tolerance=1e-4, max_iter=3)
