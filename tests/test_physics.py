"""Service model: channel values by hand, a served-ratio case small enough to compute by hand, properties."""
import dataclasses
import math

import pytest
import torch
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from dswm.sim.physics import ServiceParams, jain_index, los_probability, path_loss_db, served_ratio, service
from dswm.sim.scenario import load_scenario

from conftest import ROOT

BASE = ServiceParams.from_scenario(load_scenario(ROOT / "config.yaml", standin=True))  # docs/PROTOCOL.md §1

C0 = 299_792_458.0


def hand_los(theta_deg):
    return 1.0 / (1.0 + 9.61 * math.exp(-0.16 * (theta_deg - 9.61)))


def hand_rate(dist_m, share_hz):
    theta = math.degrees(math.asin(100.0 / dist_m))
    p = hand_los(theta)
    pl = 20 * math.log10(4 * math.pi * 2e9 * dist_m / C0) + p * 1.0 + (1 - p) * 20.0
    snr = 0.5 * 10 ** (-pl / 10) / (10**-20.4 * share_hz)
    return share_hz * math.log2(1 + snr)


def test_los_probability_at_chosen_angles():
    # 1 / (1 + 9.61 exp(-0.16 (theta - 9.61))), theta in degrees
    assert los_probability(45.0, BASE.los_a, BASE.los_b) == pytest.approx(1 / (1 + 9.61 * math.exp(-0.16 * 35.39)), rel=1e-12)
    assert los_probability(45.0, BASE.los_a, BASE.los_b) == pytest.approx(0.96769, abs=1e-5)
    assert los_probability(9.61, BASE.los_a, BASE.los_b) == pytest.approx(1 / 10.61, rel=1e-12)
    assert los_probability(90.0, BASE.los_a, BASE.los_b) == pytest.approx(0.999975, abs=1e-6)
    t = torch.tensor([9.61, 45.0], dtype=torch.float64)
    assert torch.allclose(los_probability(t, BASE.los_a, BASE.los_b), torch.tensor([1 / 10.61, 0.967692], dtype=torch.float64), atol=1e-6)


def test_path_loss_at_chosen_distances():
    # Directly below at 100 m: FSPL 78.469 dB + ~1 dB LoS excess.
    assert path_loss_db(100.0, BASE) == pytest.approx(20 * math.log10(4 * math.pi * 2e9 * 100 / C0) + 1.0 + 19 * (1 - 0.999975),
                                                abs=1e-4)
    assert path_loss_db(100.0, BASE) == pytest.approx(79.469, abs=1e-3)
    # 1 km horizontal: theta = asin(100 / 1004.99) = 5.71 deg -> mostly NLoS.
    d = math.hypot(1000.0, 100.0)
    p = hand_los(math.degrees(math.asin(100 / d)))
    assert p == pytest.approx(0.0528, abs=1e-4)
    expected = 20 * math.log10(4 * math.pi * 2e9 * d / C0) + p + (1 - p) * 20
    assert path_loss_db(d, BASE) == pytest.approx(expected, rel=1e-12)
    assert float(path_loss_db(torch.tensor(d, dtype=torch.float64), BASE)) == pytest.approx(expected, rel=1e-12)


CELLS = torch.tensor([[0.0, 0.0], [300.0, 0.0], [2000.0, 0.0]], dtype=torch.float64)


def _sr(demand, pos, params, available=None, bw_logit=None):
    pos = torch.tensor(pos, dtype=torch.float64).unsqueeze(0)
    available = torch.ones(pos.shape[:2], dtype=torch.bool) if available is None else torch.tensor([available])
    res = service(torch.tensor(demand, dtype=torch.float64), pos, available, CELLS, params=params,
                  bw_logit=None if bw_logit is None else torch.tensor([bw_logit], dtype=torch.float64))
    return res


def test_two_uavs_three_cells_by_hand_unsaturated():
    u = 400.0
    params = dataclasses.replace(BASE, demand_intensity=u)
    x = [1.0, 3.0, 2.0]
    res = _sr(x, [[100.0, 0.0], [2000.0, 0.0]], params)
    # UAV 0 serves cells 0 and 1 (shares 1/4 and 3/4 of B), UAV 1 serves cell 2 with all of B.
    assert res.assoc[0].tolist() == [0, 0, 1]
    r0 = hand_rate(math.hypot(100, 100), 20e6 * 1 / 4)
    r1 = hand_rate(math.hypot(200, 100), 20e6 * 3 / 4)
    r2 = hand_rate(100.0, 20e6)
    f = [min(1, r0 / (1 * u * 5e5)), min(1, r1 / (3 * u * 5e5)), min(1, r2 / (2 * u * 5e5))]
    assert f[0] < 1 and f[1] < 1 and f[2] < 1
    expected = (1 * f[0] + 3 * f[1] + 2 * f[2]) / 6
    assert float(res.sr[0]) == pytest.approx(expected, rel=1e-9)
    assert res.rate_bps[0].tolist() == pytest.approx([r0, r1, r2], rel=1e-9)


def test_saturation_caps_fulfilment():
    # Hand values: r0 / r0_bps = 169.1 per unit of cell 0, 117.5 for cell 1, 322.3 for cell 2 -> u = 200
    # leaves cells 0 and 1 short and saturates cell 2.
    u = 200.0
    params = dataclasses.replace(BASE, demand_intensity=u)
    x = [1.0, 3.0, 2.0]
    res = _sr(x, [[100.0, 0.0], [2000.0, 0.0]], params)
    r = [hand_rate(math.hypot(100, 100), 5e6), hand_rate(math.hypot(200, 100), 15e6), hand_rate(100.0, 20e6)]
    f = [min(1, ri / (xi * u * 5e5)) for ri, xi in zip(r, x)]
    assert f[2] == 1.0 and f[0] == pytest.approx(169.111 / 200, abs=1e-4)  # cell 2 saturates, cell 0 does not
    assert res.fulfilment[0].tolist() == pytest.approx(f, rel=1e-9)
    assert float(res.sr[0]) == pytest.approx(sum(fi * xi for fi, xi in zip(f, x)) / 6, rel=1e-9)


def test_bandwidth_logit_reweights_shares():
    params = dataclasses.replace(BASE, demand_intensity=400.0)
    res = _sr([1.0, 3.0, 0.0], [[100.0, 0.0], [2000.0, 0.0]], params, bw_logit=[math.log(2.0), 0.0])
    # tau = 2: weights 1^2 and 3^2 -> shares 1/10 and 9/10 of B; cell 2 has no demand and gets nothing.
    assert res.share_hz[0].tolist() == pytest.approx([2e6, 18e6, 0.0], rel=1e-9)


def test_no_available_uav_serves_nothing_and_empty_slot_is_served():
    params = dataclasses.replace(BASE, demand_intensity=40.0)
    res = _sr([1.0, 3.0, 2.0], [[100.0, 0.0], [2000.0, 0.0]], params, available=[False, False])
    assert float(res.sr[0]) == 0.0
    res = _sr([0.0, 0.0, 0.0], [[100.0, 0.0], [2000.0, 0.0]], params)
    assert float(res.sr[0]) == 1.0


def test_unavailable_uav_is_skipped_by_association():
    params = dataclasses.replace(BASE, demand_intensity=40.0)
    res = _sr([1.0, 3.0, 2.0], [[100.0, 0.0], [2000.0, 0.0]], params, available=[True, False])
    assert res.assoc[0].tolist() == [0, 0, 0]


def test_jain_index_by_hand():
    f = torch.tensor([[1.0, 0.5, 0.9, 0.2]], dtype=torch.float64)
    x = torch.tensor([[1.0, 1.0, 1.0, 0.0]], dtype=torch.float64)
    # f~ over demand cells = [1, 0.5, 1] -> (2.5)^2 / (3 * 2.25)
    assert float(jain_index(f, x, 0.8)[0]) == pytest.approx(6.25 / 6.75, rel=1e-9)


# ------------------------------------------------------------------ properties
coords = st.floats(min_value=0.0, max_value=4000.0, allow_nan=False)
demands = st.floats(min_value=0.0, max_value=5.0, allow_nan=False)
GRID = torch.stack(torch.meshgrid(torch.arange(5) * 800.0 + 400, torch.arange(5) * 800.0 + 400, indexing="xy"),
                   -1).reshape(-1, 2).double()
PARAMS = dataclasses.replace(BASE, demand_intensity=300.0)


@settings(max_examples=60, deadline=None)
@given(pos=st.lists(st.tuples(coords, coords), min_size=1, max_size=6), x=st.lists(demands, min_size=25, max_size=25),
       logit=st.floats(-1, 1))
def test_sr_in_unit_interval(pos, x, logit):
    p = torch.tensor(pos, dtype=torch.float64).unsqueeze(0)
    sr = served_ratio(torch.tensor(x, dtype=torch.float64), p, torch.ones(1, len(pos), dtype=torch.bool), GRID,
                      params=PARAMS, bw_logit=torch.full((1, len(pos)), logit, dtype=torch.float64))
    assert 0.0 <= float(sr[0]) <= 1.0


@settings(max_examples=60, deadline=None)
@given(pos=st.lists(st.tuples(coords, coords), min_size=1, max_size=6), new=st.tuples(coords, coords),
       x=st.lists(demands, min_size=25, max_size=25))
def test_adding_a_uav_never_lowers_the_rate_of_cells_that_keep_their_uav(pos, new, x):
    xt = torch.tensor(x, dtype=torch.float64)
    p = torch.tensor(pos, dtype=torch.float64).unsqueeze(0)
    before = service(xt, p, torch.ones(1, len(pos), dtype=torch.bool), GRID, params=PARAMS)
    p2 = torch.cat([p, torch.tensor([[new]], dtype=torch.float64)], dim=1)
    after = service(xt, p2, torch.ones(1, len(pos) + 1, dtype=torch.bool), GRID, params=PARAMS)
    kept = after.assoc[0] == before.assoc[0]
    assert torch.all(after.rate_bps[0][kept] >= before.rate_bps[0][kept] * (1 - 1e-12))
    # Cells taken over by the new UAV are at least as close to their server as before.
    moved = ~kept
    d_before = (p[0][before.assoc[0]] - GRID).norm(dim=-1)
    d_after = (p2[0][after.assoc[0]] - GRID).norm(dim=-1)
    assert torch.all(d_after[moved] <= d_before[moved] + 1e-9)


def test_adding_a_uav_can_lower_a_switching_cells_rate_under_the_proportional_split():
    # The unrestricted statement is false: a low-demand cell that switches to a new UAV shares it with a
    # hotspot and gets a much smaller bandwidth share, although its link is shorter.
    cells = torch.tensor([[0.0, 0.0], [400.0, 0.0], [700.0, 0.0], [900.0, 0.0]], dtype=torch.float64)
    x = torch.tensor([0.01, 0.01, 100.0, 100.0], dtype=torch.float64)
    two = torch.tensor([[[0.0, 0.0], [1000.0, 0.0]]], dtype=torch.float64)
    three = torch.tensor([[[0.0, 0.0], [1000.0, 0.0], [550.0, 0.0]]], dtype=torch.float64)
    before = service(x, two, torch.ones(1, 2, dtype=torch.bool), cells, params=PARAMS)
    after = service(x, three, torch.ones(1, 3, dtype=torch.bool), cells, params=PARAMS)
    assert int(after.assoc[0, 1]) == 2
    assert float(after.rate_bps[0, 1]) < 0.01 * float(before.rate_bps[0, 1])


@settings(max_examples=60, deadline=None)
@given(pos=st.lists(st.tuples(st.floats(0, 1500), st.floats(0, 1500)), min_size=2, max_size=5),
       x=st.lists(st.floats(0.0, 0.05), min_size=25, max_size=25), hot=st.floats(10.0, 50.0))
def test_moving_an_idle_uav_onto_an_unserved_hotspot_raises_sr(pos, x, hot):
    # All UAVs sit in the south-west; the hotspot is the north-east cell; the last UAV is moved onto it.
    xt = torch.tensor(x, dtype=torch.float64)
    xt[24] = hot
    p = torch.tensor(pos, dtype=torch.float64).unsqueeze(0)
    on = torch.ones(1, len(pos), dtype=torch.bool)
    before = service(xt, p, on, GRID, params=PARAMS)
    assert float(before.fulfilment[0, 24]) < 0.5  # the hotspot is badly served
    moved = p.clone()
    moved[0, -1] = GRID[24]
    after = service(xt, moved, on, GRID, params=PARAMS)
    assert float(after.sr[0]) > float(before.sr[0])


@settings(max_examples=60, deadline=None)
@given(px=st.floats(0, 4000), py=st.floats(0, 4000), g=st.integers(0, 24), xg=st.floats(0.5, 3.0))
def test_sr_gradient_points_toward_demand_the_uav_can_still_gain(px, py, g, xg):
    x = torch.zeros(25, dtype=torch.float64)
    x[g] = xg
    pos = torch.tensor([[[px, py]]], dtype=torch.float64, requires_grad=True)
    res = service(x, pos, torch.ones(1, 1, dtype=torch.bool), GRID, params=dataclasses.replace(BASE, demand_intensity=3000.0))
    offset = GRID[g] - pos.detach()[0, 0]
    assume(float(offset.norm()) > 1.0)  # a UAV right above its only cell has no direction to go
    # u = 3000 asks for >= 750 Mbps, far above any 20 MHz link: the cell is never saturated.
    assert float(res.fulfilment.detach()[0, g]) < 1.0
    res.sr.sum().backward()
    grad = pos.grad[0, 0]
    cos = float(grad @ offset / (grad.norm() * offset.norm()))
    assert cos > 0.999


def test_float32_gradients_stay_finite_for_tiny_bandwidth_shares():
    # A cell with demand 1e-7 next to a hotspot under bw_logit = 1 gets a share of ~1e-13 Hz: N0 * share
    # underflows float32, and d rate / d share involves 1 / share^2. Gradients must stay finite.
    x = torch.tensor([1e-7, 5.0, 0.0], dtype=torch.float32, requires_grad=True)
    pos = torch.tensor([[[100.0, 0.0], [2000.0, 0.0]]], dtype=torch.float32, requires_grad=True)
    logit = torch.ones(1, 2, dtype=torch.float32, requires_grad=True)
    res = service(x, pos, torch.ones(1, 2, dtype=torch.bool), CELLS.float(), params=PARAMS, bw_logit=logit)
    assert float(res.share_hz[0, 0].detach()) < 1e-9
    res.sr.sum().backward()
    for grad in (x.grad, pos.grad, logit.grad):
        assert torch.isfinite(grad).all()
    # The 1 mHz floor leaves the tiny cell practically unserved (true value ~1e-12; with the floor 0.0033).
    assert float(res.fulfilment[0, 0].detach()) < 0.01


def test_gradients_are_finite_and_zero_for_a_uav_right_above_its_cell():
    pos = torch.tensor([[[300.0, 0.0]]], dtype=torch.float32, requires_grad=True)
    x = torch.tensor([0.0, 5.0, 0.0])
    res = service(x, pos, torch.ones(1, 1, dtype=torch.bool), CELLS.float(), params=dataclasses.replace(BASE, demand_intensity=3000.0))
    res.sr.sum().backward()
    assert pos.grad.tolist() == [[[0.0, 0.0]]]  # the apex of the cone: zero subgradient, not NaN
    assert float(path_loss_db(torch.tensor(100.0, dtype=torch.float64), BASE)) == pytest.approx(path_loss_db(100.0, BASE), abs=1e-9)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_association_is_the_nearest_available_uav_and_ties_go_to_the_lowest_index(dtype):
    from dswm.sim.physics import associate, nearest_pairs, nearest_pairs_tensor

    gen = torch.Generator().manual_seed(3)
    cells = (torch.rand(50, 2, generator=gen, dtype=torch.float64) * 3000).to(dtype)
    pos = (torch.rand(64, 7, 2, generator=gen, dtype=torch.float64) * 3000).to(dtype)
    avail = torch.rand(64, 7, generator=gen) > 0.3
    avail[:, 0] = True
    dist = torch.cdist(cells.double().unsqueeze(0).expand(64, -1, -1), pos.double())
    nearest = dist.masked_fill(~avail.unsqueeze(1), float("inf")).argmin(-1)
    assert torch.equal(associate(pos, avail, cells), nearest)
    # The compiled CPU kernel and the tensor version (other devices) give the brute-force nearest UAV and its
    # squared distance, bit for bit the same.
    idx_k, d2_k = nearest_pairs(pos, avail, cells)
    idx_t, d2_t = nearest_pairs_tensor(pos, avail, cells)
    assert torch.equal(idx_k, nearest) and torch.equal(idx_t, nearest)
    assert d2_k.dtype == dtype and torch.equal(d2_k, d2_t)
    assert torch.allclose(d2_k.double(), torch.gather(dist, 2, nearest.unsqueeze(-1)).squeeze(-1) ** 2, rtol=1e-5)
    # UAVs 2 and 5 at the same spot, alone near the cells: every cell goes to UAV 2. UAV 1 is as close as UAV 2
    # but unavailable. Without any available UAV the index is 0, with UAV 0's distance (and the service model
    # serves nothing).
    far, near = [5e4, 5e4], [100.0, 100.0]
    twin = torch.tensor([[far, near, near, far, far, near, far]] * 2, dtype=dtype)
    twin_avail = torch.tensor([[True, False, True, True, True, True, True], [False] * 7])
    for fn in (nearest_pairs, nearest_pairs_tensor):
        idx, d2 = fn(twin, twin_avail, cells[:5])
        assert idx.tolist() == [[2] * 5, [0] * 5]
        far_d2 = ((cells[:5] - torch.tensor(far, dtype=dtype)) ** 2).sum(-1)
        assert torch.allclose(d2[1], far_d2) and not torch.allclose(d2[0], far_d2)


def test_a_second_process_loads_the_compiled_association_kernel_from_the_cache(tmp_path):
    """Every job is a process of its own: the first compiles the kernels (serial and parallel, float32), later ones
    load them from numba's disk cache instead of compiling again (dswm.sim.kernels)."""
    import json
    import os
    import subprocess
    import sys

    code = ("import json, torch\n"
            "from dswm.sim import kernels\n"
            "pos = torch.rand(3, 4, 2) * 1000\n"
            "for threads in (1, 2):\n"
            "    torch.set_num_threads(threads)\n"
            "    kernels._nearest(pos, torch.ones(3, 4, dtype=torch.bool), torch.rand(9, 2) * 1000)\n"
            "stats = {f: getattr(kernels, f).stats for f in ('_nearest_serial', '_nearest_parallel')}\n"
            "print(json.dumps({f: [sum(s.cache_hits.values()), sum(s.cache_misses.values())] "
            "for f, s in stats.items()}))\n")
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path), "NUMBA_NUM_THREADS": "2"}
    runs = [json.loads(subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                                      check=True).stdout) for _ in range(2)]
    assert runs[0] == {"_nearest_serial": [0, 1], "_nearest_parallel": [0, 1]}   # compiled and saved
    assert runs[1] == {"_nearest_serial": [1, 0], "_nearest_parallel": [1, 0]}   # loaded, nothing compiled
    assert any(p.suffix == ".nbi" for p in tmp_path.rglob("*"))
