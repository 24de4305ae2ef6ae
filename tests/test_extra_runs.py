"""The extra runs behind paper Figs. 8 (b) and 10: the do(s) probe's imagined demand, the variants' settings slices
(which variants train again), the reference rows on the same days, and the two figures' numbers."""
import dataclasses

import numpy as np
import polars as pl
import pytest
import torch
import yaml

from conftest import ROOT
from dswm import settings as S
from dswm.figures.ablation import do_probe_days, draw_ablation
from dswm.figures.common import read_csv
from dswm.figures.scaling import draw_scaling, scaling_days
from dswm.figures.variants import first_days
from dswm.methods import registry
from dswm.methods.base import DayContext
from dswm.methods.dswm import planner as planner_mod
from dswm.methods.dswm.modules import symlog
from dswm.methods.dswm.planner import ImaginedWorld, StepScoring, imagined_step
from dswm.methods.dswm.rssm import RSSMConfig
from dswm.methods.dswm.world_model import WorldModel, WorldModelConfig
from dswm.sim.core import FleetCore, Grid, fleet_state_from_obs, initial_positions
from dswm.sim.env import synthetic_demand
from dswm.sim.physics import ServiceParams


@pytest.fixture(scope="module")
def settings():
    config = yaml.safe_load((ROOT / "config.yaml").read_text())
    config["profile"] = "smoke"
    # the paper's sweeps (the smoke budget keeps one point off each reference): three values of each
    config["figures"]["budgets"]["smoke"] = {"seeds": [0], "eval_days": {"id": 1, "ood": 0}}
    return S.resolve(config)


# ---- the do(s) probe: imagined demand x s at decision time -------------------------------------------------
def _constant_head_model(scenario, grid, maps):
    """A physics-head world model whose E demand heads output the fixed maps (E, G) whatever the latent state."""
    cfg = WorldModelConfig(rssm=RSSMConfig(deter=16, stoch=4, hidden=16, embed=16, min_std=0.1, free_bits=0.1,
                                           kl_dyn=0.8, kl_rep=0.2),
                           ensemble=maps.shape[0], demand_hidden=8, demand_rank=4, enc_channels=4, head_hidden=16,
                           ema_nu=0.9, lambda_var=1.0, m_var=0.1, beta_kl=1.0, lambda_lpr=1.0, lambda_cal=0.1,
                           lambda_serve=1.0, service_head="physics")
    model = WorldModel(cfg=cfg, rows=grid.rows, cols=grid.cols, n_uavs=scenario.n_uavs, window=7,
                       cells=grid.cells(), params=ServiceParams.from_scenario(scenario))
    with torch.no_grad():
        model.demand.w2.zero_()
        model.demand.b2.zero_()
        model.demand.bias.copy_(symlog(maps))
    return model


@pytest.mark.parametrize("s", [0.5, 2.0])
@torch.no_grad()
def test_scaled_imagination_scores_s_times_the_imagined_demand(scenario, s):
    """imagine_scale = s multiplies the anchored imagined map by s (the uncertainty, relative, stays), so the
    served ratio the physics head scores changes; with given maps (the persistence and perfect planners) the same."""
    torch.manual_seed(0)
    grid = Grid(rows=6, cols=6, cell_m=500.0)
    g, k, rho = grid.n_cells, scenario.n_uavs, 0.95
    maps = torch.rand(3, g) * 2.0
    model = _constant_head_model(scenario, grid, maps)
    x_now = torch.rand(g)
    fleet = fleet_state_from_obs(np.concatenate([np.random.default_rng(0).uniform(0, 1, (k, 2)),
                                                 np.full((k, 1), 0.8), np.tile([[1, 0, 0, 0]], (k, 1))], 1),
                                 grid, scenario).expand(4)
    act = torch.rand(4, k, 3) * 2 - 1
    world = ImaginedWorld(cells=grid.cells(), geom=grid.geometry(), scenario=scenario,
                          params=ServiceParams.from_scenario(scenario))
    common = dict(x_prev=None, assoc=None, x_now=x_now, world=world, first=True)

    def scoring(scale=1.0, lambda_u=0.0):
        return StepScoring(rho=rho, lambda_u=lambda_u, continuation="hold", scale=scale)

    state = model.rssm.initial(4)
    *_, x1, _, r1 = imagined_step(model, fleet, state, act, x_true=None, scoring=scoring(), **common)
    *_, xs, _, rs = imagined_step(model, fleet, state, act, x_true=None, scoring=scoring(s), **common)
    want = s * (rho * x_now + (1 - rho) * maps.mean(0))           # s x the anchored ensemble mean, by hand
    torch.testing.assert_close(xs, want.expand(4, -1), rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(xs, s * x1)
    assert float((rs - r1).abs().max()) > 1e-3                    # the physics head serves another demand
    # the uncertainty term is relative to the scored demand: the same u at every s
    u1 = -imagined_step(model, fleet, state, act, x_true=None, scoring=scoring(lambda_u=1.0), **common)[-1] + r1
    us = -imagined_step(model, fleet, state, act, x_true=None, scoring=scoring(s, 1.0), **common)[-1] + rs
    torch.testing.assert_close(us, u1)
    assert float(u1.min()) > 0
    truth = torch.rand(g) + 0.1
    *_, t1, _, _ = imagined_step(None, fleet, None, act, x_true=truth, scoring=scoring(), **common)
    *_, ts, _, _ = imagined_step(None, fleet, None, act, x_true=truth, scoring=scoring(s), **common)
    torch.testing.assert_close(ts, s * t1)


def test_a_do_variant_reaches_the_controllers_imagination(settings, scenario, monkeypatch):
    """The do(s) variant's settings build a controller whose planner scores s x the map it imagines (here the
    persistence planner's current map), through the controller interface."""
    seen = []

    def spy(*args, **kwargs):
        out = imagined_step(*args, **kwargs)
        demand = out[3]                                            # (N, G), or (G,) for given maps
        seen.append((demand if demand.dim() == 1 else demand[0]).clone())
        return out

    monkeypatch.setattr(planner_mod, "imagined_step", spy)
    grid = Grid(rows=9, cols=9, cell_m=500.0)
    demand = synthetic_demand(days=1, rows=9, cols=9, seed=4) + 0.01
    core = FleetCore(demand=demand, grid=grid, scenario=scenario, dataset="do-test", day_labels=["a"],
                     init_pos=initial_positions(demand.mean((0, 1)), grid, scenario.n_uavs, 0))
    ctx = DayContext(dataset="do-test", day=0, label="a", split="id", grid=grid, scenario=scenario,
                     geometry=core.geom, cells=core.cells, init_pos=core.init_pos.numpy())
    first = {}
    for s in (1.0, 2.0):
        m = S.variant_settings(settings, S.Variant("do", s), "dswm_plus_persist").methods["dswm_plus_persist"]
        assert m.options.planner.imagine_scale == s
        ctl = registry.build(m.name, target=m.target, options=m.options, seed=0, device="cpu")
        obs = core.reset([0])
        ctl.reset(ctx)
        seen.clear()
        ctl.act({k: v[0] for k, v in obs.items()})
        first[s] = seen[0]
    x_now = torch.as_tensor(np.asarray(obs["demand"][0, -1]), dtype=torch.float32).reshape(-1)
    torch.testing.assert_close(first[1.0], x_now)
    torch.testing.assert_close(first[2.0], 2.0 * x_now)


# ---- the variants' settings slices ----------------------------------------------------------------------
def test_variants_and_which_of_them_train_again(settings):
    """A do(s) variant's train slice is the main one's (imagine_scale is a decision-time setting: no training);
    K changes the scenario (the action size) and u the reward, so DSWM trains again; non-learners never train."""
    names = [v.name for v in S.extra_variants(settings)]
    assert names == ["do0.5", "do2", "K2", "K8", "u0.5", "u2"]    # s = 1, K = 16, u x 1 are the main runs
    assert [S.parse_variant(n) for n in names] == S.extra_variants(settings)
    for bad in ("do", "K2.5", "x2", "u0", "do-1"):
        with pytest.raises(ValueError, match="do<s>, K<integer> or u<factor>"):
            S.parse_variant(bad)
    do2, k8, u2 = S.Variant("do", 2.0), S.Variant("K", 8), S.Variant("u", 2.0)
    for method in ("dswm", "dswm_wo_dec"):
        assert S.variant_train_slice(settings, method, do2) == S.train_slice(settings, method)
        assert not S.variant_retrains(settings, method, do2)
        ev = S.variant_evaluate_slice(settings, method, do2)
        assert ev["method"]["options"]["planner"]["imagine_scale"] == 2.0
        assert S.evaluate_slice(settings, method)["method"]["options"]["planner"]["imagine_scale"] == 1.0
    k_slice = S.variant_train_slice(settings, "dswm", k8)
    assert k_slice != S.train_slice(settings, "dswm") and k_slice["scenario"]["n_uavs"] == 8
    assert settings.scenario.n_uavs == 16
    u_slice = S.variant_train_slice(settings, "dswm", u2)
    assert u_slice["intensity_scale"] == 2.0 and u_slice["scenario"] == S.train_slice(settings, "dswm")["scenario"]
    assert S.variant_retrains(settings, "dswm", k8) and S.variant_retrains(settings, "dswm", u2)
    assert not S.variant_retrains(settings, "greedy", k8) and not S.variant_retrains(settings, "static", u2)
    ev = S.variant_evaluate_slice(settings, "greedy", u2)
    assert ev["intensity_scale"] == 2.0 and ev["eval_days"] == {"id": 1, "ood": 0}   # figures.eval_days (smoke)
    with pytest.raises(S.ConfigError, match="figures.do_probe.methods.*'greedy'.*imagine_scale"):
        S.variant_evaluate_slice(settings, "greedy", do2)
    jobs = S.extra_jobs(settings)
    assert len(jobs) == 2 * 2 + 4 * 3 and ("do0.5", "dswm_wo_dec", 0) in jobs and ("K2", "static", 0) in jobs


def test_the_u_factor_applies_after_calibration(scenario):
    assert scenario.demand_intensity == pytest.approx(65.58)           # conftest: the demo calibration stands in
    assert S.scale_intensity(scenario, 0.5).demand_intensity == pytest.approx(32.79)
    assert S.scale_intensity(scenario, 1.0) is scenario
    with pytest.raises(ValueError, match="calibrate"):
        S.scale_intensity(dataclasses.replace(scenario, demand_intensity="calibrate"), 2.0)


# ---- the reference rows and the two figures --------------------------------------------------------------
def _days(method, seed, srs, *, splits=("id", "id", "ood"), days=(10, 11, 13), **cols):
    return pl.DataFrame({"day": list(days), "split": list(splits), "sr_mean": list(srs), "method": method,
                         "seed": seed, "data_source": "demo", **cols},
                        schema_overrides={"day": pl.Int32, "seed": pl.Int32})


def test_reference_rows_are_the_first_days_of_each_split():
    main = pl.concat([_days("dswm", 0, [0.8, 0.7, 0.9]), _days("dswm", 1, [0.6, 0.5, 0.95])])
    cut = first_days(main, S.EvalDayLimits(id=1, ood=0))
    assert cut.select("seed", "day", "sr_mean").rows() == [(0, 10, 0.8), (1, 10, 0.6)]
    assert first_days(main, S.EvalDayLimits(id=None, ood=None)).height == 6
    with pytest.raises(ValueError, match="2 id day.*asks 3"):
        first_days(main, S.EvalDayLimits(id=3, ood=0))


def test_ablation_figure_numbers(tmp_path):
    """Panel (a): each seed's mean day, then mean and std over seeds; panel (b): s = 1 from the main results on the
    do runs' days (the first ID day here)."""
    ablation = pl.concat([_days("dswm", 0, [0.8, 0.7, 0.9]), _days("dswm", 1, [0.6, 0.5, 0.95]),
                          _days("dswm_wo_dec", 0, [0.5, 0.5, 0.6]), _days("dswm_wo_dec", 1, [0.7, 0.7, 0.6])])
    runs = pl.concat([_days(m, s, [v], splits=("id",), days=(10,), variant=name)
                      for m, s, v, name in [("dswm", 0, 0.7, "do0.5"), ("dswm", 1, 0.5, "do0.5"),
                                            ("dswm", 0, 0.9, "do2"), ("dswm", 1, 0.6, "do2"),
                                            ("dswm_wo_dec", 0, 0.4, "do2"), ("dswm_wo_dec", 1, 0.4, "do2")]])
    probe = do_probe_days(ablation, runs, methods=["dswm", "dswm_wo_dec"], seeds=[0, 1],
                          limits=S.EvalDayLimits(id=1, ood=0))
    assert probe.filter(pl.col("scale") == 1.0).height == 4          # 2 methods x 2 seeds x 1 day
    out = {ext: tmp_path / f"ablation.{ext}" for ext in ("png", "pdf", "csv")}
    draw_ablation(ablation, probe, order=["dswm", "dswm_wo_unc", "dswm_wo_dec"],
                  labels={"dswm": "DSWM", "dswm_wo_dec": "w/o dec"}, split_labels={"id": "Weekday", "ood": "Holiday"},
                  profile="demo", source="demo", out=out)
    assert out["png"].stat().st_size > 10_000 and out["pdf"].stat().st_size > 1000
    csv = read_csv(out["csv"])
    row = csv.filter((pl.col("panel") == "a") & (pl.col("method") == "dswm") & (pl.col("split") == "id")).row(
        0, named=True)
    # seeds' means 0.75 and 0.55: mean 0.65, sample std (ddof=1, as in the tables) 0.1 * sqrt(2)
    assert row["sr_mean"] == pytest.approx(0.65) and row["sr_mean_std"] == pytest.approx(0.1 * 2 ** 0.5)
    assert row["seeds"] == 2
    b = {(r["method"], r["scale"]): (r["sr_mean"], r["sr_mean_std"])
         for r in csv.filter(pl.col("panel") == "b").iter_rows(named=True)}
    assert b[("dswm", 1.0)] == pytest.approx((0.7, 0.1 * 2 ** 0.5))   # day 10: 0.8 and 0.6
    assert b[("dswm", 2.0)] == pytest.approx((0.75, 0.15 * 2 ** 0.5))
    assert b[("dswm_wo_dec", 1.0)] == pytest.approx((0.6, 0.1 * 2 ** 0.5))
    assert b[("dswm_wo_dec", 2.0)] == pytest.approx((0.4, 0.0))
    assert ("dswm_wo_dec", 0.5) not in b and len(b) == 5


def test_reference_on_other_days_than_the_runs_is_refused():
    main = _days("dswm", 0, [0.8, 0.7, 0.9])
    runs = _days("dswm", 0, [0.7], splits=("id",), days=(11,), variant="do2")
    with pytest.raises(ValueError, match="do\\(s\\) probe.*same days"):
        do_probe_days(main, runs, methods=["dswm"], seeds=[0], limits=S.EvalDayLimits(id=1, ood=0))


def test_scaling_figure_numbers(tmp_path):
    """Both sweeps hold the scenario's own point (K = 16, u x 1): the main result on the same days stands there."""
    main = pl.concat([_days(m, 0, [v, 0.0, 0.0]) for m, v in (("dswm", 0.8), ("greedy", 0.75))])
    spec = [("K2", 0.2, 0.25), ("K8", 0.6, 0.55), ("u0.5", 0.9, 0.85), ("u2", 0.5, 0.45)]
    runs = pl.concat([_days(m, 0, [v], splits=("id",), days=(10,), variant=name)
                      for name, d, g in spec for m, v in (("dswm", d), ("greedy", g))])
    days = scaling_days(main, runs, methods=["dswm", "greedy"], seeds=[0], limits=S.EvalDayLimits(id=1, ood=0),
                        n_uavs=16, fleet_sizes=[2, 8, 16], intensity_scales=[0.5, 1.0, 2.0])
    out = {ext: tmp_path / f"scaling.{ext}" for ext in ("png", "pdf", "csv")}
    table = draw_scaling(days, order=["dswm", "greedy"], labels={"dswm": "DSWM", "greedy": "Greedy"},
                         split_labels={"id": "Weekday", "ood": "Holiday"}, reference={"K": 16, "u": 1.0},
                         profile="demo", source="demo", out=out)
    assert out["png"].stat().st_size > 10_000 and out["pdf"].stat().st_size > 1000
    csv = read_csv(out["csv"])
    assert csv.height == table.height == 2 * 2 * 3
    got = {(r["sweep"], r["method"], r["value"]): r["sr_mean"] for r in csv.iter_rows(named=True)}
    assert got[("K", "dswm", 16.0)] == got[("u", "dswm", 1.0)] == pytest.approx(0.8)   # the main run's first ID day
    assert got[("K", "greedy", 2.0)] == pytest.approx(0.25) and got[("u", "greedy", 0.5)] == pytest.approx(0.85)
    assert [r["value"] for r in csv.filter((pl.col("sweep") == "K") & (pl.col("method") == "dswm")).iter_rows(
        named=True)] == [2.0, 8.0, 16.0]
