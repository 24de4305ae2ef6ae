"""Fleet dynamics, battery state machine, environment determinism, API checkers and bad input."""
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env
from pettingzoo.test import parallel_api_test

import gymnasium as gym
from dswm.sim.energy import hover_power
from dswm.sim.scenario import load_scenario
from dswm.sim.core import FleetCore, Grid, fleet_state_from_obs, initial_batteries, initial_positions
from dswm.sim.env import UAVFleetEnv, UAVFleetParallelEnv, synthetic_demand
from dswm.sim.fleet import ACTIVE, CHARGING, RETURNING, FleetState, Geometry, fleet_step

from conftest import ROOT

GRID = Grid(rows=20, cols=20, cell_m=235.0)
ROTOR = load_scenario(ROOT / "config.yaml").rotor


def _core(scenario, days=3, **kw):
    demand = synthetic_demand(days=days, rows=20, cols=20, slots=scenario.slots_per_day)
    init = initial_positions(demand.mean(axis=(0, 1)), GRID, scenario.n_uavs, 0)
    return FleetCore(demand=demand, grid=GRID, scenario=scenario, init_pos=init, dataset="test",
                     day_labels=[f"d{i}" for i in range(days)], **kw)


def test_hovering_uav_returns_after_17th_slot_charges_6_and_comes_back_full(make_scenario):
    scenario = make_scenario(n_uavs=1)
    geom = Geometry(width_m=4700.0, height_m=4700.0)
    state = FleetState(pos=torch.tensor([[1000.0, 1000.0]], dtype=torch.float64),
                       battery_j=torch.tensor([1_972_800.0], dtype=torch.float64),
                       status=torch.tensor([ACTIVE]), charge_left=torch.tensor([0]))
    statuses, energies = [], []
    for _ in range(25):
        state, energy = fleet_step(state, torch.zeros(1, 3, dtype=torch.float64), geom, scenario)
        statuses.append(int(state.status[0]))
        energies.append(float(energy[0]))
    # 0.85 * 1,972,800 J / 101,090 J per slot = 16.6: still above the reserve after 16 slots, below after 17.
    assert statuses[:16] == [ACTIVE] * 16
    assert statuses[16] == RETURNING
    assert statuses[17:23] == [CHARGING] * 6
    assert statuses[23] == ACTIVE
    assert energies[0] == pytest.approx(hover_power(ROTOR) * 600.0, rel=1e-9)
    assert energies[18:23] == [0.0] * 5
    # Back at the nearest station (1175, 1175) with a full battery.
    assert state.pos[0].tolist() == pytest.approx([1175.0, 1175.0])
    # Full at slot 24, then one more hovering slot.
    assert float(state.battery_j[0]) == pytest.approx(1_972_800.0 - hover_power(ROTOR) * 600.0, rel=1e-9)


def test_return_flight_energy_by_hand(make_scenario):
    from dswm.sim.energy import rotor_power
    scenario = make_scenario(n_uavs=1)
    geom = Geometry(width_m=4700.0, height_m=4700.0)
    state = FleetState(pos=torch.tensor([[1175.0 + 3000.0, 1175.0]], dtype=torch.float64),
                       battery_j=torch.tensor([100_000.0], dtype=torch.float64),
                       status=torch.tensor([RETURNING]), charge_left=torch.tensor([0]))
    state2, energy = fleet_step(state, torch.zeros(1, 3, dtype=torch.float64), geom, scenario)
    # Nearest station to (4175, 1175) is (3525, 1175): 650 m at 25 m/s = 26 s, then hover 574 s.
    assert float(energy[0]) == pytest.approx(rotor_power(25.0, ROTOR) * 26.0 + hover_power(ROTOR) * 574.0, rel=1e-9)
    assert state2.pos[0].tolist() == pytest.approx([3525.0, 1175.0])
    assert int(state2.status[0]) == CHARGING and int(state2.charge_left[0]) == 6


def test_displacement_is_norm_clipped_and_kept_in_area(make_scenario):
    scenario = make_scenario(n_uavs=2)
    geom = Geometry(width_m=4700.0, height_m=4700.0)
    state = FleetState(pos=torch.tensor([[2000.0, 2000.0], [4600.0, 100.0]], dtype=torch.float64),
                       battery_j=torch.full((2,), 1.9e6, dtype=torch.float64),
                       status=torch.zeros(2, dtype=torch.long), charge_left=torch.zeros(2, dtype=torch.long))
    action = torch.tensor([[1.0, 1.0, 0.0], [1.0, -1.0, 0.0]], dtype=torch.float64)
    nxt, energy = fleet_step(state, action, geom, scenario)
    step = 1500.0 / np.sqrt(2)
    assert nxt.pos[0].tolist() == pytest.approx([2000.0 + step, 2000.0 + step])
    assert nxt.pos[1].tolist() == pytest.approx([4700.0, 0.0])  # clipped to the area
    from dswm.sim.energy import rotor_power
    assert float(energy[0]) == pytest.approx(rotor_power(1500.0 / 600.0, ROTOR) * 600.0, rel=1e-9)
    assert float(energy[1]) == pytest.approx(rotor_power(np.hypot(100.0, 100.0) / 600.0, ROTOR) * 600.0, rel=1e-9)


def test_staggered_hovering_fleet_spends_1_1_to_1_3_mj_per_slot(scenario):
    core = _core(scenario)
    core.reset([0])
    energies = []
    for _ in range(scenario.slots_per_day - 1):
        out = core.step(np.zeros((1, scenario.n_uavs, 3), dtype=np.float32))
        energies.append(float(out.energy_j[0]))
    assert out.truncated[0] and not out.terminated[0]  # the day's end cuts the episode; nothing terminates it
    mean_mj = np.mean(energies) / 1e6
    assert 1.1 <= mean_mj <= 1.3


def test_initial_batteries_evenly_spaced_and_permuted_by_day(scenario):
    a = initial_batteries("milan", "2013-12-21", scenario)
    b = initial_batteries("milan", "2013-12-21", scenario)
    c = initial_batteries("milan", "2013-12-22", scenario)
    assert np.array_equal(a, b)
    assert np.sort(a) == pytest.approx(np.linspace(0.5, 1.0, 16) * 1_972_800.0)
    assert not np.array_equal(a, c)


def test_initial_positions_follow_demand():
    demand = np.zeros((20, 20))
    demand[2, 3] = 5.0
    demand[15, 17] = 5.0
    pos = initial_positions(demand, GRID, 2, 0)
    centres = sorted(map(tuple, np.round(pos, -1)))
    assert centres[0] == pytest.approx((3.5 * 235, 2.5 * 235), abs=20)
    assert centres[1] == pytest.approx((17.5 * 235, 15.5 * 235), abs=20)


def test_core_is_deterministic_and_observation_round_trips(scenario):
    rng = np.random.default_rng(7)
    actions = rng.uniform(-1, 1, (20, 2, scenario.n_uavs, 3)).astype(np.float32)
    runs = []
    for _ in range(2):
        core = _core(scenario)
        obs = core.reset([0, 2])
        srs = [core.sr0.copy()]
        for a in actions:
            out = core.step(a)
            srs.append(out.sr)
        runs.append(np.stack(srs))
        recovered = fleet_state_from_obs(out.obs["fleet"], GRID, scenario)
        assert torch.allclose(recovered.pos, core.state.pos, atol=1e-3)
        assert torch.equal(recovered.status, core.state.status)
    assert np.array_equal(runs[0], runs[1])
    assert obs["demand"].shape == (2, 7, 20, 20)
    # Before slot 6 the window is edge-padded with the day's first map.
    assert np.array_equal(obs["demand"][0, 0], obs["demand"][0, 6])


def test_gymnasium_and_pettingzoo_checkers_pass():
    check_env(gym.make("dswm/UAVFleet-v0").unwrapped, skip_render_check=True)
    parallel_api_test(UAVFleetParallelEnv(), num_cycles=150)


def test_gym_env_same_seed_same_episode():
    def run():
        env = UAVFleetEnv()
        obs, info = env.reset(seed=3)
        env.action_space.seed(3)
        total = 0.0
        for _ in range(30):
            obs, r, term, trunc, info = env.step(env.action_space.sample())
            total += r
        return info["day"] if "day" in info else None, total
    assert run() == run()


@pytest.mark.parametrize("bad, message", [
    (lambda d: d.__setitem__((0, 5, 1, 1), np.nan), "non-finite value nan at day 0, slot 5, row 1, col 1"),
    (lambda d: d.__setitem__((1, 2, 3, 4), -1.0), "negative demand -1.0 at day 1, slot 2, row 3, col 4"),
])
def test_bad_demand_is_refused(scenario, bad, message):
    demand = synthetic_demand(days=2, rows=20, cols=20)
    bad(demand)
    with pytest.raises(ValueError, match=message.replace("(", r"\(")):
        FleetCore(demand=demand, grid=GRID, scenario=scenario, init_pos=np.zeros((16, 2)), dataset="x",
                  day_labels=["a", "b"])


def test_wrong_shapes_are_refused(scenario):
    with pytest.raises(ValueError, match=r"expected shape \('days', 144, 20, 20\), found \(2, 144, 10, 10\)"):
        FleetCore(demand=synthetic_demand(days=2), grid=GRID, scenario=scenario, init_pos=np.zeros((16, 2)),
                  dataset="x", day_labels=["a", "b"])
    core = _core(scenario)
    core.reset([0])
    with pytest.raises(ValueError, match=r"action: expected shape \(1, 16, 3\), found \(16, 3\)"):
        core.step(np.zeros((16, 3)))


def test_nan_action_refused_and_out_of_range_clipped(scenario):
    core = _core(scenario)
    core.reset([0])
    a = np.zeros((1, 16, 3), dtype=np.float32)
    a[0, 4, 1] = np.nan
    with pytest.raises(ValueError, match="non-finite value nan at episode 0, UAV 4, component 1"):
        core.step(a)
    big = np.full((1, 16, 3), 5.0, dtype=np.float32)
    one = np.ones((1, 16, 3), dtype=np.float32)
    c1, c2 = _core(scenario), _core(scenario)
    c1.reset([0]), c2.reset([0])
    assert np.array_equal(c1.step(big).sr, c2.step(one).sr)


def test_uav_load_splits_the_served_demand_among_the_uavs(scenario):
    core = _core(scenario, days=2)
    core.reset([0, 1])
    rng = np.random.default_rng(3)
    for _ in range(4):
        out = core.step(rng.uniform(-1, 1, size=(2, scenario.n_uavs, 3)).astype(np.float32))
    x = core.demand[core.days, core.t].reshape(2, -1).numpy()
    assert core.uav_load.shape == (2, scenario.n_uavs)
    assert (core.uav_load >= 0).all()
    # Every served unit is served by exactly one UAV: the per-UAV loads add up to SR times the total demand.
    np.testing.assert_allclose(core.uav_load.sum(-1), out.sr * x.sum(-1), rtol=1e-5)
    assert (core.uav_load > 0).sum() > 1
