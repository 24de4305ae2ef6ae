"""Static, greedy and oracle: lattice, moves checked against a one-candidate-at-a-time search, clairvoyance."""
import numpy as np
import pytest
import torch

from dswm.methods.classical import GreedyController, OracleController, StaticController
from dswm.methods.search import SearchSettings, lattice_offsets
from dswm.methods.base import DayContext
from dswm.sim.core import Grid, build_observation
from dswm.sim.fleet import ACTIVE, CHARGING, FleetState
from dswm.sim.physics import ServiceParams, served_ratio

GRID = Grid(rows=12, cols=12, cell_m=235.0)  # 2820 m square


def ctx(scn, init_pos, demand=None, day=0):
    return DayContext(dataset="toy", day=day, label=f"d{day}", split="id", grid=GRID, scenario=scn,
                      geometry=GRID.geometry(), cells=GRID.cells(), init_pos=np.asarray(init_pos, np.float32),
                      demand=demand)


def observe(scn, pos, x_now, *, status=None, slot=0):
    """Observation of one day: fleet at ``pos`` (K, 2), current map ``x_now`` (R, C) (window filled with it)."""
    k = len(pos)
    state = FleetState(pos=torch.tensor(np.asarray(pos), dtype=torch.float32)[None],
                       battery_j=torch.full((1, k), scn.battery_j),
                       status=torch.tensor([status if status is not None else [ACTIVE] * k]),
                       charge_left=torch.zeros(1, k, dtype=torch.long))
    window = torch.tensor(np.asarray(x_now, np.float32))[None, None].expand(1, scn.obs_window + 1, *x_now.shape)
    return {key: v[0] for key, v in build_observation(window, state, torch.tensor([slot]), GRID, scn).items()}


def hotspot(r, c, value=5.0, background=0.01):
    x = np.full((GRID.rows, GRID.cols), background, np.float32)
    x[r, c] = value
    return x


def test_lattice_has_the_reachable_points_of_a_7x7_grid():
    off = lattice_offsets(7, 1500.0)
    # points (500 i, 500 j) with i^2 + j^2 <= 9: 7 + 2*5 + 2*5 + 2*1 = 29
    assert off.shape == (29, 2)
    assert torch.equal(off[0], torch.zeros(2))
    assert float(torch.linalg.vector_norm(off, dim=-1).max()) == pytest.approx(1500.0)
    assert {round(float(v)) for v in off.flatten()} == {-1500, -1000, -500, 0, 500, 1000, 1500}


def test_static_flies_back_to_its_spot_at_most_d_max_per_slot(make_scenario):
    scn = make_scenario(n_uavs=2)
    init = np.array([[500.0, 500.0], [2000.0, 2000.0]])
    ctrl = StaticController(name="static")
    ctrl.reset(ctx(scn, init))
    # UAV 0 is 1000 m north of its spot, UAV 1 is on its spot
    a = ctrl.act(observe(scn, [[500.0, 1500.0], [2000.0, 2000.0]], hotspot(0, 0)))
    assert a.shape == (2, 3)
    assert a[0, :2] * scn.d_max_m == pytest.approx([0.0, -1000.0], abs=0.5)
    assert a[1] == pytest.approx([0.0, 0.0, 0.0], abs=1e-4)
    far = ctrl.act(observe(scn, [[2800.0, 2800.0], [2000.0, 2000.0]], hotspot(0, 0)))
    assert np.linalg.norm(far[0, :2]) == pytest.approx(1.0, abs=1e-5)  # full D_max towards (500, 500)
    assert far[0, 0] == pytest.approx(far[0, 1], abs=1e-5) and far[0, 0] < 0


def reference_bcd(scn, pos, x, sweeps, lattice):
    """Greedy's search one candidate fleet at a time (no batching): the plan (K, 2) it should reach."""
    params = ServiceParams.from_scenario(scn)
    cells, geom = GRID.cells(), GRID.geometry()
    pos = torch.tensor(np.asarray(pos), dtype=torch.float32)
    plan = pos.clone()
    avail = torch.ones(1, len(pos), dtype=torch.bool)
    xt = torch.tensor(x.reshape(-1))
    for _ in range(sweeps):
        for j in range(len(pos)):
            best, best_sr = None, -1.0
            for off in lattice_offsets(lattice, scn.d_max_m):
                trial = plan.clone()
                trial[j] = geom.clip(pos[j] + off)
                sr = float(served_ratio(xt, trial[None], avail, cells, params=params)[0])
                if sr > best_sr:
                    best, best_sr = trial[j].clone(), sr
            plan[j] = best
    return plan.numpy(), best_sr


def test_greedy_reaches_the_plan_of_a_one_candidate_at_a_time_search(make_scenario):
    scn = make_scenario(n_uavs=3, demand_intensity=200.0)
    rng = np.random.default_rng(4)
    x = rng.gamma(0.5, 1.0, size=(GRID.rows, GRID.cols)).astype(np.float32)
    pos = np.array([[300.0, 400.0], [1500.0, 2500.0], [2600.0, 900.0]])
    ctrl = GreedyController(name="greedy", options=SearchSettings(sweeps=2, lattice=5, refine=0, bw_logits=()))
    ctrl.reset(ctx(scn, pos))
    action = ctrl.act(observe(scn, pos, x))
    expected, expected_sr = reference_bcd(scn, pos, x, sweeps=2, lattice=5)
    np.testing.assert_allclose(pos + action[:, :2] * scn.d_max_m, expected, atol=0.05)
    assert np.all(action[:, 2] == 0.0)  # demand-proportional split
    # ... and the plan serves the current map at least as well as holding position
    params = ServiceParams.from_scenario(scn)
    hold = float(served_ratio(torch.tensor(x.reshape(-1)), torch.tensor(pos, dtype=torch.float32)[None],
                              torch.ones(1, 3, dtype=torch.bool), GRID.cells(), params=params)[0])
    assert expected_sr >= hold


def test_greedy_heads_for_the_current_hotspot_and_the_oracle_for_the_next_one(make_scenario):
    scn = make_scenario(n_uavs=1, demand_intensity=500.0)
    start = [[1410.0, 1410.0]]  # centre of the area
    west, east = hotspot(6, 0), hotspot(6, 11)  # row 6, westmost / eastmost column
    day = np.stack([west, east] + [east] * (scn.slots_per_day - 2))
    greedy = GreedyController(name="greedy", options=SearchSettings(sweeps=2, lattice=7, refine=0, bw_logits=()))
    greedy.reset(ctx(scn, start))
    oracle = OracleController(name="oracle", options=SearchSettings(sweeps=2, lattice=7, refine=1, bw_logits=[0.0, 1.0]))
    oracle.reset(ctx(scn, start, demand=day))
    obs = observe(scn, start, west, slot=0)  # at slot 0 the next map x_1 is the eastern hotspot
    dx_greedy = greedy.act(obs)[0, 0] * scn.d_max_m
    dx_oracle = oracle.act(obs)[0, 0] * scn.d_max_m
    # the hotspot cell centres are 1292.5 m west / east of the start: each flies most of the way to its own
    assert dx_greedy < -1000.0
    assert dx_oracle > 1000.0


def test_oracle_refuses_a_day_without_its_true_demand(make_scenario):
    scn = make_scenario(n_uavs=1)
    oracle = OracleController(name="oracle", options=SearchSettings(sweeps=1, lattice=3, refine=0, bw_logits=[0.0]))
    with pytest.raises(ValueError, match="clairvoyant"):
        oracle.reset(ctx(scn, [[0.0, 0.0]]))
    with pytest.raises(ValueError, match=r"^config key search\.bw_logits: expected \[\] \(the demand-proportional "
                                         r"split\) or a list of bandwidth logits in \[-1, 1\] that includes 0, "
                                         r"found \[0\.5\]$"):
        OracleController(name="oracle", options=SearchSettings(sweeps=1, lattice=3, refine=0, bw_logits=[0.5]))


def test_charging_uavs_are_not_moved_and_batched_days_match_single_days(make_scenario):
    scn = make_scenario(n_uavs=3, demand_intensity=200.0)
    rng = np.random.default_rng(7)
    maps = [rng.gamma(0.5, 1.0, size=(GRID.rows, GRID.cols)).astype(np.float32) for _ in range(2)]
    pos = [[300.0, 400.0], [1500.0, 2500.0], [2600.0, 900.0]]
    status = [ACTIVE, CHARGING, ACTIVE]
    single = []
    for d, x in enumerate(maps):
        g = GreedyController(name="greedy", options=SearchSettings(sweeps=2, lattice=5, refine=0, bw_logits=()))
        g.reset(ctx(scn, pos, day=d))
        single.append(g.act(observe(scn, pos, x, status=status)))
    assert np.all(single[0][1] == 0.0)
    g = GreedyController(name="greedy", options=SearchSettings(sweeps=2, lattice=5, refine=0, bw_logits=()))
    g.reset_batch([ctx(scn, pos, day=d) for d in range(2)])
    obs = [observe(scn, pos, x, status=status) for x in maps]
    batched = g.act_batch({k: np.stack([o[k] for o in obs]) for k in obs[0]})
    np.testing.assert_allclose(batched, np.stack(single), atol=1e-6)


def test_oracle_bandwidth_search_never_serves_less_than_the_proportional_split(make_scenario):
    scn = make_scenario(n_uavs=2, demand_intensity=300.0)
    rng = np.random.default_rng(11)
    x_next = rng.gamma(0.3, 1.0, size=(GRID.rows, GRID.cols)).astype(np.float32)
    day = np.stack([x_next] * scn.slots_per_day)
    pos = [[700.0, 700.0], [2100.0, 2100.0]]
    levels = [-1.0, -0.5, 0.0, 0.5, 1.0]
    oracle = OracleController(name="oracle", options=SearchSettings(sweeps=2, lattice=5, refine=1, bw_logits=levels))
    oracle.reset(ctx(scn, pos, demand=day))
    a = oracle.act(observe(scn, pos, x_next))
    assert set(np.round(a[:, 2], 6)) <= set(levels)
    params = ServiceParams.from_scenario(scn)
    moved = torch.tensor(np.asarray(pos) + a[:, :2] * scn.d_max_m, dtype=torch.float32)[None]
    args = (torch.tensor(x_next.reshape(-1)), moved, torch.ones(1, 2, dtype=torch.bool), GRID.cells())
    with_bw = float(served_ratio(*args, params=params, bw_logit=torch.tensor(a[None, :, 2]))[0])
    without = float(served_ratio(*args, params=params)[0])
    assert with_bw >= without - 1e-6
