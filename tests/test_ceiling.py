"""The per-slot ceiling: its settings, its search, and that it bounds the controllers with the environment's physics."""
import copy
import dataclasses

import numpy as np
import polars as pl
import pytest
import torch

from dswm import settings as runconfig
from dswm.config import load_yaml
from dswm.methods.base import DayContext
from dswm.methods.ceiling import CeilingController, CeilingSettings, area_lattice, ceiling_search
from dswm.methods.classical import OracleController, StaticController
from dswm.methods.search import SearchSettings
from dswm.protocol.evaluation import evaluate, write_days
from dswm.sim.core import Grid, core_from_tensor
from dswm.sim.physics import ServiceParams, served_ratio
from test_evaluation import RUN, toy_tensor

from conftest import ROOT

GRID = Grid(rows=6, cols=6, cell_m=235.0)
SETTINGS = CeilingSettings(sweeps=4, lattice=9, keep=2, refine=3, chains=2, fresh=1, polish=0,
                           bw_logits=[-1.0, -0.5, 0.0, 0.5, 1.0])
LIGHT = dataclasses.replace(SETTINGS, sweeps=2, lattice=5, refine=1)
"""For the tests that evaluate whole days: every stage of the search (chains, keep, fresh) runs, in a third of the
time."""
SEARCH = SearchSettings(sweeps=2, lattice=7, refine=2, bw_logits=[-1.0, -0.5, 0.0, 0.5, 1.0])


def test_the_ceiling_is_a_clairvoyant_upper_bound_with_its_own_section_and_no_shared_search():
    config = load_yaml(ROOT / "config.yaml")
    s = runconfig.resolve(config)
    m = s.methods["ceiling"]
    assert (m.controller_class, m.label, m.table_class, m.learns) == (CeilingController, "Ceiling (clairvoyant)",
                                                                     "upper bound", False)
    section = {k: v for k, v in config["ceiling"].items() if k != "budgets"}
    assert m.options == CeilingSettings(**section)  # the demo (default) and the paper run the section as written
    assert runconfig.resolve({**config, "profile": "paper"}).methods["ceiling"].options == m.options
    smoke = runconfig.resolve({**config, "profile": "smoke"}).methods["ceiling"].options  # CI's weaker search
    assert smoke == CeilingSettings(**{**section, **config["ceiling"]["budgets"]["smoke"]})
    assert (smoke.lattice, smoke.chains) < (m.options.lattice, m.options.chains)
    ctl = CeilingController(name="ceiling", options=m.options)
    assert ctl.clairvoyant and ctl.places and ctl.deterministic
    assert ctl.search_settings() is None  # its search is its own: the controllers' one `search` does not apply
    with pytest.raises(NotImplementedError, match="per-slot bound"):
        ctl.act_batch({})


@pytest.mark.parametrize("key, value, expected", [
    ("lattice", 1, "an integer >= 2"),
    ("chains", 0, "an integer >= 1"),
    ("keep", 0, "an integer >= 1"),
    ("fresh", 0, "an integer >= 1"),
    ("refine", -1, "an integer >= 0"),
    ("polish", -1, "an integer >= 0"),
    ("bw_logits", [0.5], "a non-empty list of bandwidth logits in [-1, 1] that includes 0"),
])
def test_a_wrong_ceiling_value_is_refused_with_its_key_the_expected_form_and_what_was_found(key, value, expected):
    bad = copy.deepcopy(load_yaml(ROOT / "config.yaml"))
    bad["ceiling"][key] = value
    with pytest.raises(runconfig.ConfigError) as err:
        runconfig.validate_config(bad, runconfig.load_schema(runconfig.SCHEMA))
    assert f"config.yaml: key 'ceiling.{key}' must be {expected}; found {value!r}" in str(err.value)


def test_doubling_doubles_every_setting_and_halves_the_logit_step():
    d = dataclasses.replace(SETTINGS, polish=2).doubled()
    assert (d.sweeps, d.lattice, d.keep, d.refine, d.chains, d.fresh, d.polish) == (8, 18, 4, 6, 4, 2, 4)
    assert sorted(d.bw_logits) == [-1.0, -0.75, -0.5, -0.25, 0.0, 0.25, 0.5, 0.75, 1.0]
    assert d.bw_logits[0] == 0.0  # 0 first: a tie keeps the demand-proportional split


def test_doubling_only_named_settings_leaves_the_others_and_names_an_unknown_one():
    d = SETTINGS.doubled(["chains", "bw_logits"])
    assert (d.sweeps, d.lattice, d.keep, d.refine, d.chains, d.fresh, d.polish) == (4, 9, 2, 3, 4, 1, 0)
    assert sorted(d.bw_logits) == [-1.0, -0.75, -0.5, -0.25, 0.0, 0.25, 0.5, 0.75, 1.0]
    with pytest.raises(ValueError) as err:
        SETTINGS.doubled(["chain"])
    assert str(err.value) == ("ceiling: cannot double ['chain']; the settings are ['sweeps', 'lattice', 'keep', "
                              "'refine', 'polish', 'chains', 'fresh', 'bw_logits']")


def test_polish_searches_the_slots_best_placement_again_with_finer_rounds_and_never_serves_less(make_scenario):
    """The first slot of each toy day (the same starts with and without polish): the polished placement serves at
    least what the plain search's best one serves, more on some day, and is what the search reaches from that best
    placement with refine + polish rounds."""
    scn = make_scenario(n_uavs=3, demand_intensity=150.0)
    t = toy_tensor()
    params = ServiceParams.from_scenario(scn)
    polished = dataclasses.replace(SETTINGS, polish=3)

    def first_slot(opts, ctx, x, cells):
        """The placement and logits (as tensors) the ceiling at ``opts`` gives slot 1 of ``ctx``, and their served
        ratio on that slot's map ``x``."""
        ctl = CeilingController(name="ceiling", options=opts)
        ctl.reset_batch([ctx])
        pos, logit = (torch.as_tensor(a) for a in ctl.place_batch({}))
        sr = served_ratio(x, pos, torch.ones(1, 3, dtype=torch.bool), cells, params=params, bw_logit=logit)
        return pos, logit, float(sr[0])

    gains = []
    for day in range(t.demand.shape[0]):
        core = core_from_tensor(t, scn, [day])
        ctx, cells = toy_context(core, t, scn, day), core.grid.cells()
        x = torch.as_tensor(t.demand[day][1].reshape(1, -1))
        pos, logit, plain = first_slot(SETTINGS, ctx, x, cells)
        fine = first_slot(polished, ctx, x, cells)[2]
        again = ceiling_search(x, pos.unsqueeze(1), logit.unsqueeze(1), cells=cells, geom=core.grid.geometry(),
                               settings=dataclasses.replace(SETTINGS, refine=6), params=params)[2]
        assert fine == pytest.approx(float(again[0, 0]), abs=1e-6), day
        gains.append(fine - plain)
    assert min(gains) >= -1e-6, gains
    assert max(gains) > 1e-4, gains


def test_the_lattice_spans_the_whole_area_cell_centred():
    pts = area_lattice(4, 1000.0, 2000.0)
    assert pts.shape == (16, 2)
    assert sorted({float(v) for v in pts[:, 0]}) == [125.0, 375.0, 625.0, 875.0]
    assert sorted({float(v) for v in pts[:, 1]}) == [250.0, 750.0, 1250.0, 1750.0]


def test_the_search_finds_two_far_hotspots_that_no_one_slot_reach_joins(make_scenario):
    """Two UAVs at the south-west corner, demand in the two far corners only, too much for any UAV to serve in full
    (so the nearer the better): the search puts one right above each."""
    scn = make_scenario(n_uavs=2, demand_intensity=300.0)
    x = torch.zeros(1, GRID.n_cells)
    x[0, 5] = 50.0  # row 0, col 5: the south-east corner cell
    x[0, 35] = 50.0  # row 5, col 5: the north-east corner cell
    start = torch.tensor([[[[100.0, 100.0], [150.0, 100.0]]]])  # (B=1, S=1, K=2, 2)
    pos, logit, sr = ceiling_search(x, start, torch.zeros(1, 1, 2), settings=SETTINGS, cells=GRID.cells(),
                                    geom=GRID.geometry(), params=ServiceParams.from_scenario(scn))
    corners = GRID.cells()[[5, 35]]
    near = torch.cdist(pos[0, 0], corners)  # (K, 2 corners)
    assert float(near.min(dim=0).values.max()) < 30.0  # each corner has a UAV within 30 m (3 rounds: 20 m steps)
    apart = served_ratio(x, start[:, 0], torch.ones(1, 2, dtype=torch.bool), GRID.cells(),
                         params=ServiceParams.from_scenario(scn), bw_logit=logit[:, 0])
    assert float(sr[0, 0]) > 5 * float(apart[0])


def toy_context(core, tensor, scn, day):
    """The context of ``day`` of the toy tensor for a core built on that day (its grid and initial fleet), with the
    day's true demand (the ceiling is clairvoyant)."""
    grid = core.grid
    return DayContext(dataset="toy", day=day, label=f"d{day}", split="id", grid=grid, scenario=scn,
                      geometry=grid.geometry(), cells=grid.cells(), init_pos=core.init_pos.numpy(),
                      demand=tensor.demand[day])


def oracle_and_ceiling_slot_by_slot(scn, tensor, day):
    """Served ratio per slot of the oracle (flying, batteries) and of the ceiling (placed) on one day, each on its
    own core; the ceiling's checked against the physics called directly on its placement."""
    cores = [core_from_tensor(tensor, scn, [day]) for _ in range(2)]
    grid = cores[0].grid
    ctx = toy_context(cores[0], tensor, scn, day)
    oracle = OracleController(name="oracle", options=SEARCH)
    ceiling = CeilingController(name="ceiling", options=SETTINGS)
    obs = [c.reset([0]) for c in cores]
    oracle.reset_batch([ctx])
    ceiling.reset_batch([ctx])
    params = ServiceParams.from_scenario(scn)
    sr_o, sr_c, charging = [cores[0].sr0[0]], [cores[1].sr0[0]], 0
    for t in range(scn.slots_per_day - 1):
        out_o = cores[0].step(oracle.act_batch(obs[0]))
        pos, logit = ceiling.place_batch(obs[1])
        out_c = cores[1].place(pos, logit)
        obs = [out_o.obs, out_c.obs]
        x = torch.as_tensor(tensor.demand[day][t + 1].reshape(1, -1))
        direct = served_ratio(x, torch.as_tensor(pos), torch.ones(1, scn.n_uavs, dtype=torch.bool), grid.cells(),
                              params=params, bw_logit=torch.as_tensor(logit))
        assert out_c.sr[0] == float(direct[0])  # the very physics the environment serves with, no second one
        assert np.isnan(out_c.energy_j).all()  # a placed fleet flies nothing
        sr_o.append(out_o.sr[0])
        sr_c.append(out_c.sr[0])
        charging += int((cores[0].state.status != 0).any())
    return np.array(sr_o), np.array(sr_c), charging


def test_the_ceiling_serves_at_least_what_the_oracle_serves_in_every_slot(make_scenario):
    scn = make_scenario(n_uavs=3, demand_intensity=150.0)
    t = toy_tensor()
    sr_o, sr_c, charging = oracle_and_ceiling_slot_by_slot(scn, t, 3)
    assert charging > 0  # the oracle's fleet loses UAVs to charging on this day; the ceiling's never does
    assert sr_c[0] == sr_o[0]  # slot 0: the initial deployment serves, for every method
    assert (sr_c >= sr_o - 1e-6).all(), np.flatnonzero(sr_c < sr_o - 1e-6)
    assert sr_c.mean() > sr_o.mean() + 0.01


def test_the_evaluation_of_the_ceiling_writes_a_result_like_the_others_without_energy(make_scenario, tmp_path):
    scn = make_scenario(n_uavs=3, demand_intensity=150.0)
    t = toy_tensor()
    kw = dict(tensor=t, scenario=scn, seed=0, limits={"id": 1, "ood": 1}, profile="smoke", **RUN)
    res = evaluate(controller=CeilingController(name="ceiling", options=LIGHT), **kw)
    static = evaluate(controller=StaticController(name="static"), **kw).days
    days = res.days
    assert days.columns == static.columns and days.schema == static.schema
    assert days["energy_kj_per_slot"].null_count() == days["energy_efficiency"].null_count() == 2
    assert (days["sr_mean"] > static["sr_mean"]).all()
    # slot 0 of the trace is the initial deployment, as every method's; every UAV is always active
    np.testing.assert_allclose(res.trajectories["id_pos"][0], core_from_tensor(t, scn, [3]).init_pos.numpy())
    assert (res.trajectories["id_status"] == 0).all()
    # deterministic: another seed gives the same numbers
    again = evaluate(controller=CeilingController(name="ceiling", seed=5, options=LIGHT), **{**kw, "seed": 5}).days
    assert again["sr_mean"].to_list() == days["sr_mean"].to_list()
    record = {"method": "ceiling", "train_source": None, "model": None, "model_sha256": None, "train_manifest": None}
    write_days(days, tmp_path / "days.parquet", record,
               {"method": "ceiling", "class": "dswm.methods.ceiling:CeilingController", "options": {}, "search": None})
    assert pl.read_parquet(tmp_path / "days.parquet")["energy_kj_per_slot"].dtype == pl.Float64


def test_a_placement_of_the_wrong_shape_or_with_nan_is_refused(make_scenario):
    scn = make_scenario(n_uavs=3)
    core = core_from_tensor(toy_tensor(), scn, [3])
    core.reset([0])
    with pytest.raises(ValueError, match=r"placement pos: expected shape \(1, 3, 2\), found \(1, 2, 2\)"):
        core.place(np.zeros((1, 2, 2)), np.zeros((1, 3)))
    with pytest.raises(ValueError, match="placement bw_logit: non-finite value at episode 0, UAV 2"):
        core.place(np.zeros((1, 3, 2)), np.array([[0.0, 0.0, np.nan]]))
    assert core.t == 0  # nothing moved


def test_a_days_ceiling_depends_on_that_day_alone_not_on_the_days_evaluated_beside_it(make_scenario):
    """Sparse maps (about 70% of the cells empty, other ones each day): each day's ceiling is the same number
    whether it is evaluated alone or batched with another, as the profiles' day limits batch them."""
    scn = make_scenario(n_uavs=3, demand_intensity=150.0)
    t = toy_tensor()
    t.demand[:] *= np.random.default_rng(1).random(t.demand.shape) < 0.3
    kw = dict(tensor=t, scenario=scn, seed=0, limits={"id": None, "ood": None}, profile="smoke", **RUN)
    def ceiling(days):
        return evaluate(controller=CeilingController(name="ceiling", options=LIGHT), **{**kw, "days": days}).days

    together = ceiling({"id": [3, 4]})
    for row in together.iter_rows(named=True):
        assert ceiling({"id": [row["day"]]})["sr_mean"].to_list() == [row["sr_mean"]], row["label"]
