"""JTORATC: KKT bandwidth, the rate surrogate, the BCD's objective, actions, solver failures, the degradation rule,
and the per-day stats hook of the evaluation."""
import dataclasses
import logging
import math

import cvxpy as cp
import numpy as np
import polars as pl
import pytest
import torch

from dswm.methods.base import DayContext
from dswm.methods.classical import StaticController
from dswm.methods.jtoratc import JTORATCController, JTORATCSettings
from dswm.methods.jtoratc.controller import solve_slot
from dswm.methods.jtoratc.model import (LN2, Z_MIN_M2, Slot, concave_bridges, kkt_bandwidth, log_snr_hz,
                                        rate_surrogate, shannon_rate)
from dswm.methods.jtoratc.sca import TrajectoryProgram, induced_slack
from dswm.protocol.evaluation import DAY_COLUMNS, evaluate, write_days
from dswm.sim.core import Grid, core_from_tensor
from dswm.sim.energy import rotor_constants, rotor_power
from dswm.sim.physics import ServiceParams
from test_evaluation import toy_tensor

GRID = Grid(rows=6, cols=6, cell_m=235.0)  # toy_tensor's grid
SETTINGS = JTORATCSettings(w_delay=1.0, w_energy=1.0, w_load=1.0, bcd_iters=3, bcd_tol=1e-3, assoc_iters=50,
                           sca_iters=3, sca_tol=1e-4, trust_region_m=500.0, solver="CLARABEL",
                           solve_budget_ms=1.0e9, degrade_every=6, degraded_sca_iters=1)


@pytest.fixture
def scn(make_scenario):
    return make_scenario(n_uavs=3, demand_intensity=150.0)


def params_of(scn):
    return ServiceParams.from_scenario(scn)


def z_max(grid=GRID):
    g = grid.geometry()
    return g.width_m**2 + g.height_m**2


# ---------------------------------------------------------------------------------------------- bandwidth (KKT)
def test_kkt_bandwidth_meets_the_closed_form_of_two_cells(scenario):
    """Two cells share B; the KKT point is where w1 R1'(B1) / R1(B1)^2 = w2 R2'(B - B1) / R2(B - B1)^2. Choosing
    B1* and w1, that equation gives w2 in closed form; the bisection must return B1*. A second UAV's pair, with
    another split, is solved in the same call (one multiplier per UAV)."""
    p = params_of(scenario)
    total = p.bandwidth_hz
    v = log_snr_hz(np.array([150.0, 900.0, 40.0, 2500.0]) ** 2, p)  # ln S of four cells at these distances

    def marginal(b, vv):  # R'(B) / R(B)^2 of the Shannon rate
        y = math.exp(vv) / b
        r = b * math.log1p(y) / LN2
        return (math.log1p(y) - y / (1.0 + y)) / LN2 / r**2

    b1, b3 = 0.3 * total, 0.8 * total
    w = np.array([1.0, marginal(b1, v[0]) / marginal(total - b1, v[1]), 2.0,
                  2.0 * marginal(b3, v[2]) / marginal(total - b3, v[3])])
    share = kkt_bandwidth(w, v, np.array([0, 0, 1, 1]), 2, total)
    np.testing.assert_allclose(share, [b1, total - b1, b3, total - b3], rtol=1e-7)
    # ... and it is the minimum of the delay over every split of the first pair (a scan of 10^5 splits)
    grid = np.linspace(1e-3, 1 - 1e-3, 100_001) * total
    scan = w[0] / shannon_rate(grid, v[0]) + w[1] / shannon_rate(total - grid, v[1])
    best = w[0] / shannon_rate(share[0], v[0]) + w[1] / shannon_rate(share[1], v[1])
    assert best <= scan.min() * (1 + 1e-12)


# ---------------------------------------------------------------------------------------------- rate surrogate
def test_the_rate_surrogate_is_a_lower_bound_tight_at_the_expansion_point(scenario):
    p = params_of(scenario)
    zm = 2 * 4700.0**2  # the demo grid's squared diagonal
    bridges = concave_bridges(p, zm)
    # ln S is not convex in z where the LoS probability turns fastest: at h = 100 m, 51.7-165.5 m horizontally
    assert len(bridges) == 1
    assert math.sqrt(bridges[0].za) == pytest.approx(51.66, abs=0.05)
    assert math.sqrt(bridges[0].zb) == pytest.approx(165.46, abs=0.05)
    # ... where the plain tangent in z overshoots the rate, so it would be no lower bound
    zmid, zfar = 100.0**2, 60.0**2
    v0, dv = log_snr_hz(zmid, p, slope=True)
    assert float(v0 + dv * (zfar - zmid)) > float(log_snr_hz(zfar, p))

    rng = np.random.default_rng(0)
    n = 20_000
    z0 = rng.uniform(0, 1, n) ** 3 * zm  # many points near the UAV, where the bridge is
    z = rng.uniform(0, 1, n) ** 3 * zm
    share = 10 ** rng.uniform(1, math.log10(p.bandwidth_hz), n)
    a, b = rate_surrogate(share, z0, p, bridges)
    rate = shannon_rate(share, log_snr_hz(z, p))
    rate0 = shannon_rate(share, log_snr_hz(z0, p))
    assert np.all(b <= 0)  # concave in the UAV position
    assert np.all(a + b * z <= rate * (1 + 1e-12))  # a lower bound everywhere
    off = (z0 >= Z_MIN_M2) & ~((z0 > bridges[0].za) & (z0 < bridges[0].zb))
    assert off.sum() > 0.9 * n
    np.testing.assert_allclose((a + b * z0)[off], rate0[off], rtol=1e-10)  # tight at the expansion point
    gap = 1 - (a + b * z0) / rate0
    assert np.all(gap >= -1e-12) and gap.max() < 0.01  # on the bridge: below, by less than 1 %


def test_zeng_slack_gives_the_rotor_power_at_the_expansion_point(scenario):
    rotor = scenario.rotor
    p0, p_i, v0 = rotor_constants(rotor)
    speed = np.array([0.0, 1.0, 2.5, 10.0, 25.0])
    y = induced_slack(speed, rotor)
    np.testing.assert_allclose(1 / y**2, y**2 + speed**2 / v0**2, rtol=1e-12)  # Zeng et al.'s equality
    drag = 0.5 * rotor.fuselage_drag_ratio * rotor.air_density * rotor.rotor_solidity * rotor.disc_area_m2
    power = p0 * (1 + 3 * speed**2 / rotor.tip_speed_mps**2) + p_i * y + drag * speed**3
    np.testing.assert_allclose(power, rotor_power(torch.tensor(speed), rotor).numpy(), rtol=1e-12)


# ---------------------------------------------------------------------------------------------- the BCD
def make_slot(scn, grid, x, pos, weights=(1.0, 1.0, 1.0)):
    g = grid.geometry()
    pos = np.asarray(pos, dtype=np.float64)
    k = len(pos)
    return Slot(x=np.asarray(x, np.float64).reshape(-1), cells=grid.cells(dtype=torch.float64).numpy(), start=pos,
                stay=pos, avail=np.ones(k, bool), movable=np.ones(k, bool), params=params_of(scn), rotor=scn.rotor,
                slot_s=scn.slot_s, d_max_m=scn.d_max_m, width_m=g.width_m, height_m=g.height_m, weights=weights)


def program_for(scn, grid, settings=SETTINGS):
    g = grid.geometry()
    return TrajectoryProgram(cells=grid.cells(dtype=torch.float64).numpy(), n_uavs=scn.n_uavs, width_m=g.width_m,
                             height_m=g.height_m, rotor=scn.rotor, slot_s=scn.slot_s,
                             weights=(settings.w_delay, settings.w_energy), solver=settings.solver)


def test_the_bcd_objective_never_rises_and_the_plan_lowers_it(scn):
    grid = Grid(rows=8, cols=8, cell_m=235.0)
    rng = np.random.default_rng(3)
    x = rng.gamma(0.5, 1.0, size=(8, 8))
    x[x < 0.05] = 0.0  # some cells without demand
    slot = make_slot(scn, grid, x, [[300.0, 300.0], [400.0, 1600.0], [1700.0, 500.0]])
    plan = solve_slot(slot, SETTINGS, program=program_for(scn, grid), bridges=concave_bridges(
        slot.params, z_max(grid)), sca_iters=SETTINGS.sca_iters)
    trace = np.array(plan.trace)
    assert len(trace) == 1 + 2 * plan.rounds
    assert np.all(np.diff(trace) <= 1e-12 * trace[0])  # a minimization: J never rises
    assert trace[-1] < 0.9 * trace[0]  # and the fleet, badly placed, gains
    moved = np.linalg.norm(plan.pos - slot.start, axis=1)
    assert moved.max() > 100.0 and np.all(moved <= scn.d_max_m + 1e-6)
    assert np.all(np.abs(plan.logit) <= 1.0)


# ---------------------------------------------------------------------------------------------- the controller
def day_context(scn, tensor, day, init_pos):
    g = GRID
    return DayContext(dataset="toy", day=day, label=f"d{day}", split="id", grid=g, scenario=scn, geometry=g.geometry(),
                      cells=g.cells(), init_pos=init_pos)


def run_slots(ctrl, scn, n_slots, day=3):
    """Step ``ctrl`` ``n_slots`` slots of one toy day through the environment; returns actions and positions."""
    tensor = toy_tensor()
    core = core_from_tensor(tensor, scn, [day])
    obs = core.reset([0])
    ctrl.reset(day_context(scn, tensor, day, core.init_pos.cpu().numpy()))
    actions, pos = [], [core.state.pos[0].numpy().astype(np.float64)]
    for _ in range(n_slots):
        a = ctrl.act({k: v[0] for k, v in obs.items()})
        actions.append(a)
        obs = core.step(a[None]).obs
        pos.append(core.state.pos[0].numpy().astype(np.float64))
    return np.stack(actions), np.stack(pos)


def test_actions_stay_in_bounds_and_within_d_max_and_repeat_exactly(scn):
    ctrl = JTORATCController(name="jtoratc", options=SETTINGS)
    actions, pos = run_slots(ctrl, scn, 4)
    assert actions.shape == (4, 3, 3) and actions.dtype == np.float32
    assert np.all(np.abs(actions) <= 1.0)
    assert np.all(np.linalg.norm(actions[..., :2], axis=-1) <= 1.0 + 1e-6)
    assert np.all(np.linalg.norm(np.diff(pos, axis=0), axis=-1) <= scn.d_max_m * (1 + 1e-5))
    assert np.abs(actions[..., :2]).max() > 0.05  # it does move
    again, _ = run_slots(JTORATCController(name="jtoratc", options=SETTINGS), scn, 4)
    np.testing.assert_array_equal(actions, again)  # no random draw
    stats = ctrl.day_stats()[0]
    assert stats["solves"] == 4 and stats["degraded_slots"] == 0 and stats["solver_failures"] == 0


def test_a_solver_failure_keeps_the_last_positions_is_counted_and_logged_once_per_day(scn, monkeypatch, caplog):
    ctrl = JTORATCController(name="jtoratc", options=SETTINGS)
    ctrl.reset(day_context(scn, None, 3, np.zeros((3, 2), np.float32)))  # builds the program before the patch

    def broken(self, *args, **kwargs):
        raise cp.error.SolverError("solver died")

    monkeypatch.setattr(cp.Problem, "solve", broken)
    with caplog.at_level(logging.WARNING, logger="dswm.methods.jtoratc.controller"):
        actions, _ = run_slots(ctrl, scn, 3)
    stats = ctrl.day_stats()[0]
    # every round's SCA step fails: no UAV moves, each failure is counted
    assert np.all(actions[..., :2] == 0.0)
    assert stats["solves"] == 3 and stats["solver_failures"] == 3 * stats["bcd_rounds_mean"] >= 3
    warned = [r for r in caplog.records if "SCA solver failed" in r.getMessage()]
    assert len(warned) == 1 and "day d3" in warned[0].getMessage() and "solver died" in warned[0].getMessage()
    run_slots(ctrl, scn, 1, day=4)  # a new day warns again
    assert len([r for r in caplog.records if "SCA solver failed" in r.getMessage()]) == 2


def test_the_degradation_rule_solves_every_sixth_slot_once_over_budget_and_is_counted(scn):
    slow = dataclasses.replace(SETTINGS, solve_budget_ms=1e-6)  # every solve is over this budget
    ctrl = JTORATCController(name="jtoratc", options=slow)
    actions, _ = run_slots(ctrl, scn, 13)
    # solves at decisions 1, 7 and 13; the first is a full solve, the other two degraded; ten held
    assert ctrl.day_stats()[0] | {"bcd_rounds_mean": 0, "solve_ms_median": 0} == {
        "solves": 3.0, "solver_failures": 0.0, "over_budget_solves": 3.0, "degraded_slots": 12.0,
        "held_slots": 10.0, "bcd_rounds_mean": 0, "solve_ms_median": 0}
    held = [i for i in range(13) if i not in (0, 6, 12)]
    for i in held:  # the held plan's logits
        np.testing.assert_array_equal(actions[i, :, 2], actions[6 * (i // 6), :, 2])
    ctrl.reset(day_context(scn, None, 4, np.zeros((3, 2), np.float32)))  # a new day starts undegraded
    assert ctrl.day_stats()[0]["degraded_slots"] == 0 and not ctrl.degraded


# ---------------------------------------------------------------------------------------------- per-day stats
class CountingStatic(StaticController):
    """Static, batched, reporting per day the number of actions it took and its day index."""

    def reset_batch(self, ctxs):
        super().reset_batch(ctxs)
        self.days, self.n = [c.day for c in ctxs], 0

    def act_batch(self, obs):
        self.n += 1
        return super().act_batch(obs)

    def day_stats(self):
        return [{"actions": self.n, "day_index": d} for d in self.days]


def test_per_day_stats_become_days_parquet_columns_batched_or_not(scn, tmp_path):
    tensor, limits = toy_tensor(), {"id": 1, "ood": 1}
    run = {"seed": 0, "limits": limits, "profile": "smoke", "device": "cpu", "progress_interval_s": 5.0}
    slow = dataclasses.replace(SETTINGS, solve_budget_ms=1e-6, bcd_iters=1)  # degraded from the first solve: fast
    days = evaluate(tensor=tensor, controller=JTORATCController(name="jtoratc", options=slow), scenario=scn,
                    batch_days=True, **run).days
    stat_cols = ["stat_bcd_rounds_mean", "stat_degraded_slots", "stat_held_slots", "stat_over_budget_solves",
                 "stat_solve_ms_median", "stat_solver_failures", "stat_solves"]
    assert days.columns == DAY_COLUMNS + stat_cols
    # 143 decisions: solves at 1, 7, ..., 139 (24), the 119 others held, all but the first degraded
    assert days["stat_solves"].to_list() == [24.0, 24.0] and days["stat_held_slots"].to_list() == [119.0, 119.0]
    assert days["stat_degraded_slots"].to_list() == [142.0, 142.0]
    write_days(days, tmp_path / "days.parquet", {"method": "jtoratc", "train_source": None, "model": None,
                                                 "model_sha256": None, "train_manifest": None},
               {"method": "jtoratc", "class": "dswm.methods.jtoratc:JTORATCController", "options": {}, "search": None})
    back = pl.read_parquet(tmp_path / "days.parquet")
    assert back.schema["stat_solves"] == pl.Float64 and back["stat_held_slots"].to_list() == [119.0, 119.0]
    # a batched controller reports one mapping per day of its batch, in order
    for batch in (True, False):
        got = evaluate(tensor=tensor, controller=CountingStatic(name="static"), scenario=scn, batch_days=batch,
                       **run).days
        assert got["stat_day_index"].to_list() == [3.0, 5.0]
        assert got["stat_actions"].to_list() == [143.0, 143.0]


def test_a_controller_reporting_the_wrong_number_of_days_is_refused(scn):
    class Wrong(StaticController):
        def day_stats(self):
            return [{"x": 1.0}]

    with pytest.raises(ValueError, match="reported 1 day.*expected one mapping per day of the last reset \\(2\\)"):
        evaluate(tensor=toy_tensor(), controller=Wrong(name="static"), scenario=scn, seed=0,
                 limits={"id": 1, "ood": 1}, profile="smoke", device="cpu", batch_days=True, progress_interval_s=5.0)
