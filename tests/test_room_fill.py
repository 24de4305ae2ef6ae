"""DSWM+ where the room is: the per-step anchoring rho_k (its least-squares fit, the planner setting, whose default
changes no decision), the candidate's settings, and the figure's table."""

import dataclasses

import numpy as np
import polars as pl
import pytest
import torch

from dswm.config import ConfigError
from dswm.figures.room_fill import room_fill_table
from dswm.methods.dswm import quality
from dswm.methods.dswm.planner import (AnchoredCEMPlanner, ImaginationScorer, ImaginedWorld, PlannerConfig,
                                       StepScoring)
from dswm.methods.search import SearchSettings
from dswm.pipeline.room_fill import training_split, with_fit
from dswm.sim.core import fleet_state_from_obs
from test_planner import _constant_head_model, _grid_setup


def test_fit_rho_steps_recovers_a_known_optimum():
    """On maps built so that x_{t+k} = r_k x_t + (1 - r_k) m_k exactly, the least-squares
    rho_k is r_k; values beyond [0, 1] are clipped, and x_t = m_k gives persistence (1)."""
    rng = np.random.default_rng(3)
    n, g = 50, 8
    now = rng.uniform(0, 2, (n, g))
    r = np.array([0.9, 0.6, 0.2, 1.4, -0.5])
    horizon = len(r)
    model = rng.uniform(0, 2, (horizon, n, g))
    truth = np.stack([r[k] * now + (1 - r[k]) * model[k] for k in range(horizon)])
    # a day whose start slots are every (H + 1)-th: x_t at the start, then the truths of steps 1..H
    demand = np.zeros((n * (horizon + 1), g))
    starts = np.arange(n) * (horizon + 1)
    demand[starts] = now
    for j in range(horizon):
        demand[starts + j + 1] = truth[j]
    moments = quality.anchor_moments(model, demand, starts)
    rho = quality.fit_rho_steps(moments)
    np.testing.assert_allclose(rho, [0.9, 0.6, 0.2, 1.0, 0.0], atol=1e-12)
    mse = quality.anchored_mse(moments, rho)
    np.testing.assert_allclose(mse[:3], 0.0, atol=1e-12)        # the anchored map is the truth
    assert (quality.anchored_mse(moments, 0.95)[:3] > 1e-3).all()  # a fixed rho is not
    # sums add over days: two copies give the same rho and mse
    both = quality.add_moments(moments, moments)
    np.testing.assert_allclose(quality.fit_rho_steps(both), rho)
    np.testing.assert_allclose(quality.anchored_mse(both, rho), mse)
    # x_t equal to the model's map: no information, persistence
    same = quality.anchor_moments(np.stack([now] * horizon), demand, starts)
    assert quality.fit_rho_steps(same).tolist() == [1.0] * horizon


def test_fit_rho_steps_matches_a_grid_search():
    """On random maps the fitted rho_k minimizes the anchored error of ``demand_errors`` over a fine grid."""
    rng = np.random.default_rng(1)
    demand = rng.gamma(2.0, 0.5, (60, 6))
    starts = np.arange(0, 60 - 4)
    pred = demand[starts][None] * 0.5 + rng.uniform(0, 1, (4, len(starts), 6))
    rho = quality.fit_rho_steps(quality.anchor_moments(pred, demand, starts))
    grid = np.linspace(0, 1, 2001)
    errs = np.array([quality.demand_errors(pred, demand, starts, float(r))["mse_anchored"] for r in grid])  # (R, H)
    np.testing.assert_allclose(rho, grid[errs.argmin(0)], atol=1e-3)
    np.testing.assert_allclose(quality.anchored_mse(quality.anchor_moments(pred, demand, starts), 0.95),
                               quality.demand_errors(pred, demand, starts, 0.95)["mse_anchored"], rtol=1e-10)


def test_rho_steps_default_leaves_the_planner_unchanged_and_a_list_is_used(scenario):
    """rho_steps None (every method's setting) and the list rho repeated H times give bit-identical scores and the
    same plan; another list changes the scores of the steps it anchors."""
    torch.manual_seed(0)
    grid, geom, cells, params = _grid_setup(scenario)
    g, k, horizon = grid.n_cells, scenario.n_uavs, 4
    model = _constant_head_model(scenario, grid, cells, params, torch.rand(3, g) * 2.0)
    rng = np.random.default_rng(5)
    fleet = fleet_state_from_obs(np.concatenate([rng.uniform(0, 1, (k, 2)), rng.uniform(0.2, 1.0, (k, 1)),
                                                 np.tile([[1, 0, 0, 0]], (k, 1))], 1), grid, scenario)
    world = ImaginedWorld(cells=cells, geom=geom, scenario=scenario, params=params)
    common = dict(model=model, latent=model.rssm.initial(1), fleet=fleet, x_now=torch.rand(g) * 3.0, world=world,
                  gamma=0.9, compile=False)
    actions = torch.rand(8, horizon, k, 3) * 2 - 1

    def scores(rho_steps):
        scoring = StepScoring(rho=0.95, lambda_u=1.0, continuation="lloyd", rho_steps=rho_steps)
        return ImaginationScorer(**common, scoring=scoring)(actions)

    default = scores(None)
    assert torch.equal(default, scores((0.95,) * horizon))
    assert not torch.equal(default, scores((0.95, 0.5, 0.2, 0.0)))
    cfg = PlannerConfig(horizon=horizon, n_samples=16, n_elites=4, iterations=2, sigma0=0.3, sigma0_later=0.3,
                        min_std=0.05, gamma=0.9, rho=0.95, lambda_u=1.0, warm_start=True, carry_best=True,
                        continuation="lloyd", proposal="none",
                        search=SearchSettings(sweeps=1, lattice=3, refine=0, bw_logits=(0.0,)), compile=False)
    assert cfg.rho_steps is None and cfg.rho_at(1) == 0.95 and cfg.rho_at(horizon) == 0.95
    plans = []
    for c in (cfg, dataclasses.replace(cfg, rho_steps=[0.95] * horizon)):
        scoring = StepScoring(rho=c.rho, lambda_u=c.lambda_u, continuation=c.continuation, rho_steps=c.rho_steps)
        planner = AnchoredCEMPlanner(cfg=c, n_uavs=k, device="cpu", seed=3)
        plans.append([planner.plan(ImaginationScorer(**common, scoring=scoring))[0] for _ in range(2)])
    assert all(torch.equal(a, b) for a, b in zip(*plans))
    assert dataclasses.replace(cfg, rho_steps=[0.9, 0.5, 0.2, 0.1]).rho_at(3) == 0.2


def test_rho_steps_must_have_one_value_per_step():
    base = dict(horizon=3, n_samples=16, n_elites=4, iterations=1, sigma0=0.3, sigma0_later=None, min_std=0.0,
                gamma=0.9, rho=0.95, lambda_u=1.0, warm_start=False, carry_best=False, continuation="hold",
                proposal="none", search=SearchSettings(sweeps=1, lattice=3, refine=0, bw_logits=()), compile=False)
    with pytest.raises(ConfigError, match=r"dswm.planner.rho_steps: expected 3 numbers \(one per imagined step, "
                                          r"horizon 3\), found 2"):
        PlannerConfig(**base, rho_steps=(0.5, 0.5))


class _Tensor:
    def __init__(self, train_days):
        self.train_days = train_days
        self.meta = {"dataset": "shanghai"}


def test_training_split_holds_out_the_last_training_days():
    fit, val = training_split(_Tensor(list(range(10))), 2, 3)
    assert (fit, val) == ([5, 6], [7, 8, 9])
    with pytest.raises(ValueError, match=r"shanghai: 4 training day\(s\), but figures.room_fill.fit_days \+ "
                                         r"validation_days = 5 need as many"):
        training_split(_Tensor([0, 1, 2, 3]), 2, 3)


def test_with_fit_puts_rho_k_and_gamma_in_the_planner_only():
    job = {"profile": "demo", "method": {"name": "dswm_plus", "options": {"steps": 4, "planner": {
        "gamma": 0.5, "rho": 0.95, "rho_steps": None, "horizon": 3}}}}
    out = with_fit(job, {"rho_steps": [1.0, 0.5, 0.25], "gamma": 0.9})
    assert out["method"]["options"]["planner"] == {"gamma": 0.9, "rho": 0.95, "rho_steps": [1.0, 0.5, 0.25],
                                                   "horizon": 3}
    assert out["method"]["options"]["steps"] == 4 and job["method"]["options"]["planner"]["gamma"] == 0.5


def _runs(values):
    rows = []
    for arm, per_split in values.items():
        for split, days in per_split.items():
            for day, sr in days.items():
                rows.append({"dataset": "shanghai", "arm": arm, "seed": 0, "split": split, "day": day, "sr_mean": sr})
    return pl.DataFrame(rows)


def test_room_fill_table_shares_per_split():
    runs = _runs({"greedy": {"id": {1: 0.60, 2: 0.62}, "ood": {5: 0.70}},
                  "perfect": {"id": {1: 0.70, 2: 0.72}, "ood": {5: 0.74}},
                  "dswm_plus": {"id": {1: 0.66, 2: 0.66}, "ood": {5: 0.69}}})
    table = room_fill_table(runs, arms=["greedy", "perfect", "dswm_plus"],
                            labels={"greedy": "Greedy", "perfect": "Perfect", "dswm_plus": "DSWM+"},
                            regime={"dataset": "shanghai", "d_max_m": 1500.0, "intensity_scale": 2.0},
                            split_labels={"id": "Weekday", "ood": "Holiday"})
    row = {(r["split"], r["arm"]): r for r in table.iter_rows(named=True)}
    assert row[("id", "dswm_plus")]["room"] == pytest.approx(0.10)
    assert row[("id", "dswm_plus")]["share"] == pytest.approx(0.05 / 0.10)
    assert row[("ood", "dswm_plus")]["share"] == pytest.approx(-0.01 / 0.04)
    assert row[("all", "dswm_plus")]["share"] == pytest.approx((0.67 - 0.64) / (0.72 - 0.64))
    assert row[("id", "greedy")]["share"] == 0.0 and row[("id", "perfect")]["share"] == pytest.approx(1.0)
    assert row[("ood", "dswm_plus")]["split_label"] == "Holiday" and row[("id", "dswm_plus")]["days"] == 2
    with pytest.raises(ValueError, match="arm 'dswm_plus' covers other"):
        room_fill_table(runs.filter(~((pl.col("arm") == "dswm_plus") & (pl.col("day") == 5))),
                        arms=["greedy", "perfect", "dswm_plus"], labels={"greedy": "G", "perfect": "P", "dswm_plus": "D"},
                        regime={"dataset": "shanghai", "d_max_m": 1500.0, "intensity_scale": 2.0}, split_labels={})


def _settings(profile, **room_fill):
    import copy
    from pathlib import Path

    import yaml

    from dswm import settings as S

    config = copy.deepcopy(yaml.safe_load((Path(__file__).parents[1] / "config.yaml").read_text()))
    config["profile"] = profile
    config["figures"]["room_fill"].update(room_fill)
    return S, S.resolve(config)


def test_room_fill_runs_the_profiles_test_days_in_the_regime_of_the_headroom_map():
    S, demo = _settings("demo")
    assert S.room_fill_variant(demo).name == "D1500u2"
    assert [a for _, a, _ in S.room_fill_jobs(demo)] == ["greedy", "perfect", "dswm", "dswm_plus", "dswm_plus_persist",
                                                         "dswm_plus_rhok"]
    greedy, candidate = S.room_fill_slice(demo, "greedy"), S.room_fill_slice(demo, "dswm_plus_rhok")
    assert greedy["eval_days"] == candidate["eval_days"] == {"id": 2, "ood": 1}   # the demo profile's test days
    assert greedy["intensity_scale"] == 2.0 and greedy["scenario"]["d_max_m"] == 1500.0
    assert "room_fill" in candidate and "room_fill" not in greedy
    assert candidate["method"]["options"]["planner"]["rho_steps"] is None  # until the fit's record fills it
    _, cut = _settings("demo", eval_days={"id": 1, "ood": None})
    assert S.room_fill_slice(cut, "perfect")["eval_days"] == {"id": 1, "ood": 1}
    with pytest.raises(ConfigError, match=r"key 'figures.room_fill.intensity_scale' is 3.0, which is no cell of the "
                                          r"headroom map \(figures.headroom.intensity_scales: \[1.0, 2.0\]\)"):
        _settings("demo", intensity_scale=3.0)
