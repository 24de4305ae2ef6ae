"""DSWMController through the controller interface: build from config, fit, save/load, act; ablations."""
import numpy as np
import pytest
import yaml

import dataclasses

from conftest import ROOT
from dswm import settings as runconfig
from dswm.methods import registry
from dswm.methods.base import DayContext
from dswm.sim.core import FleetCore, Grid, initial_positions
from dswm.sim.env import synthetic_demand


@pytest.fixture(scope="module")
def resolved():
    config = yaml.safe_load((ROOT / "config.yaml").read_text())
    config["profile"] = "smoke"
    return runconfig.resolve(config)


def build(method, settings, seed, **budget):
    """The method's controller from resolved settings; ``budget`` (transitions, steps) overrides the profile's."""
    m = settings.methods[method]
    return registry.build(method, target=m.target, options=dataclasses.replace(m.options, **budget), seed=seed,
                          device="cpu")


@pytest.fixture(scope="module")
def raw():
    config = yaml.safe_load((ROOT / "config.yaml").read_text())
    config["profile"] = "smoke"
    return config


@pytest.fixture(scope="module")
def core(resolved, scenario):
    assert dataclasses.replace(scenario, demand_intensity=0.0) == \
        dataclasses.replace(resolved.scenario, demand_intensity=0.0)  # config.yaml's, u a number (conftest)
    grid = Grid(rows=9, cols=9, cell_m=500.0)
    demand = synthetic_demand(days=3, rows=9, cols=9, seed=4) + 0.01
    c = FleetCore(demand=demand, grid=grid, scenario=scenario, dataset="agent-test", day_labels=["a", "b", "c"],
                  init_pos=initial_positions(demand.mean((0, 1)), grid, scenario.n_uavs, 0))
    c.day_ids = np.array([10, 11, 12])
    return c


def _ctx(core, day=0):
    return DayContext(dataset="agent-test", day=day, label=core.day_labels[day], split="id", grid=core.grid,
                      scenario=core.scenario, geometry=core.geom, cells=core.cells, init_pos=core.init_pos.numpy())


def _play(ctl, core, slots):
    obs = core.reset([0])
    ctl.reset(_ctx(core))
    out = []
    for _ in range(slots):
        a = ctl.act({k: v[0] for k, v in obs.items()})
        out.append(a)
        obs = core.step(a[None]).obs
    return np.stack(out)


def test_methods_are_configurations_of_one_controller(resolved, raw):
    built = {m: build(m, resolved, 0) for m in ("dswm", "dswm_wo_unc", "dswm_wo_dec")}
    assert {type(c).__name__ for c in built.values()} == {"DSWMController"}
    assert built["dswm"].settings.planner.lambda_u == raw["dswm"]["planner"]["lambda_u"] > 0
    assert built["dswm_wo_unc"].settings.planner.lambda_u == 0.0
    assert built["dswm_wo_dec"].settings.world_model.service_head == "mlp"
    assert built["dswm"].settings.world_model.service_head == "physics"
    s = built["dswm"].settings
    assert (s.transitions, s.steps) == (raw["dswm"]["budgets"]["smoke"]["transitions"],
                                        raw["dswm"]["budgets"]["smoke"]["steps"])


def test_a_method_override_of_the_training_section_reaches_its_settings(raw):
    import copy

    cfg = copy.deepcopy(raw)
    cfg["dswm"]["methods"]["dswm_wo_unc"]["training"] = {"lr": 3.0e-4}
    settings = runconfig.resolve(cfg)
    built = {m: build(m, settings, 0) for m in ("dswm", "dswm_wo_unc")}
    assert built["dswm_wo_unc"].settings.training.lr == 3.0e-4
    assert built["dswm"].settings.training.lr == raw["dswm"]["training"]["lr"] == 1.0e-3
    assert built["dswm_wo_unc"].settings.training.batch == raw["dswm"]["training"]["batch"]


def test_a_profile_budget_of_the_training_section_sits_under_the_methods_overrides(raw):
    """``dswm.budgets.<profile>.training`` is merged over ``dswm.training``, and a method's own ``training`` over
    both: the paper profile compiles every DSWM method's training step, the demo none, one method may opt out."""
    import copy

    cfg = copy.deepcopy(raw)
    cfg["dswm"]["budgets"]["paper"]["training"] = {"compile": True, "lr": 5.0e-4}
    cfg["dswm"]["methods"]["dswm_wo_unc"]["training"] = {"compile": False}
    paper = runconfig.resolve({**cfg, "profile": "paper"})
    demo = runconfig.resolve({**cfg, "profile": "demo"})
    assert raw["dswm"]["training"]["compile"] is False and raw["dswm"]["budgets"]["paper"]["training"] == {
        "compile": True}
    assert [paper.methods[m].options.training.compile for m in ("dswm", "dswm_plus", "dswm_wo_unc")] == [
        True, True, False]
    assert paper.methods["dswm_wo_unc"].options.training.lr == 5.0e-4   # the budget's other key stays
    assert not any(demo.methods[m].options.training.compile for m in ("dswm", "dswm_plus", "dswm_wo_unc"))
    assert demo.methods["dswm"].options.training.lr == raw["dswm"]["training"]["lr"]


@pytest.mark.parametrize("method", ["dswm", "dswm_wo_dec"])
def test_fit_save_load_act(resolved, core, tmp_path, method):
    ctl = build(method, resolved, 3, transitions=286, steps=4)
    manifest = ctl.fit(core, run_dir=tmp_path / "train")
    assert manifest["n_transitions"] == 286 and manifest["steps"] == 4
    assert sorted(set(manifest["days"])) == [10, 11] and manifest["read_test_data"] is False
    assert len(manifest["history"]["losses/dem"]) == 4
    assert (tmp_path / "train" / "training_diagnostics.png").exists()
    ctl.save(tmp_path / "model.pt")
    a = _play(ctl, core, 4)
    assert a.shape == (4, core.scenario.n_uavs, 3) and np.isfinite(a).all() and np.abs(a).max() <= 1.0
    # a loaded copy with the same seed plans the same actions
    other = build(method, resolved, 3)
    other.load(tmp_path / "model.pt")
    np.testing.assert_array_equal(_play(other, core, 4), a)


def test_a_finished_checkpoint_resumes_only_on_the_same_training_data(resolved, core, tmp_path):
    """Snakemake reruns `train` when the tensor or the scenario changed: the old checkpoint must not be reused."""
    import torch

    budget = {"transitions": 286, "steps": 3}
    first = build("dswm", resolved, 1, **budget)
    first.fit(core, run_dir=tmp_path / "train")
    weights = {k: v.clone() for k, v in first.model.state_dict().items()}
    # the same inputs again: the finished run is resumed, so not one more step changes the weights
    again = build("dswm", resolved, 1, **budget)
    again.fit(core, run_dir=tmp_path / "train")
    assert all(torch.equal(v, weights[k]) for k, v in again.model.state_dict().items())
    # other training data in the same run directory: trained anew, not the old weights
    changed = FleetCore(demand=core.demand.reshape(3, -1, 9, 9).numpy() * 1.5, grid=core.grid, scenario=core.scenario,
                        dataset="agent-test", day_labels=core.day_labels, init_pos=core.init_pos.numpy())
    changed.day_ids = core.day_ids
    fresh = build("dswm", resolved, 1, **budget)
    fresh.fit(changed, run_dir=tmp_path / "train")
    differs = [k for k, v in fresh.model.state_dict().items() if not torch.equal(v, weights[k])]
    assert "rssm.gru.weight_hh" in differs, differs


def test_dswm_is_algorithm_1_and_each_ablation_changes_one_thing(resolved, raw):
    """dswm: mean 0 and one sigma0 each slot, plain CEM, no seed; the ablations differ in one setting each."""
    built = {m: build(m, resolved, 0) for m in ("dswm", "dswm_wo_unc", "dswm_wo_dec", "dswm_plus")}
    p = built["dswm"].settings.planner
    assert (p.warm_start, p.carry_best, p.continuation, p.proposal, p.sigma0_later, p.min_std) == \
        (False, False, "hold", "none", None, 0.0)
    assert p.later_std == p.sigma0 and p.horizon == 15
    assert built["dswm"].search_settings() is None       # Algorithm 1 runs no BCD

    def diff(a, b):
        pa, pb = dataclasses.asdict(a.settings), dataclasses.asdict(b.settings)
        return {(sec, k) for sec in pa if isinstance(pa[sec], dict) for k in pa[sec] if pa[sec][k] != pb[sec][k]}

    assert diff(built["dswm"], built["dswm_wo_unc"]) == {("planner", "lambda_u")}
    assert diff(built["dswm"], built["dswm_wo_dec"]) == {("world_model", "service_head")}
    plus = built["dswm_plus"]
    assert plus.settings.planner.proposal == "bcd" and plus.settings.planner.warm_start
    assert plus.search_settings() == resolved.methods["greedy"].options   # the one shared search


def test_persistence_and_perfect_forecast_plan_on_the_maps_they_claim(resolved, core):
    """dswm_plus_persist imagines the current map held constant; perfect the true maps x_{t+1..t+H}, the last one
    standing in past the day's end; both share DSWM+'s planner and the shared search."""
    import torch

    plus = resolved.methods["dswm_plus"].options.planner
    persist, perfect = build("dswm_plus_persist", resolved, 0), build("perfect", resolved, 0)
    assert persist.settings.planner == perfect.settings.planner == plus
    assert not persist.learns and not perfect.learns and perfect.clairvoyant and not persist.clairvoyant
    h = plus.horizon
    obs = core.reset([0])
    ctx = _ctx(core)
    with pytest.raises(ValueError, match="clairvoyant"):
        perfect.reset(ctx)
    true = core.demand[0].reshape(core.demand.shape[1], -1)                 # (T, G)
    perfect.reset(dataclasses.replace(ctx, demand=core.demand[0].numpy()))
    persist.reset(ctx)
    one = {k: v[0] for k, v in obs.items()}
    demand = torch.as_tensor(np.asarray(one["demand"]), dtype=torch.float32)
    fleet = core.state.__class__(*(t[0] for t in core.state))
    scorer, first = persist._scorer(one, demand, fleet)
    torch.testing.assert_close(scorer.override, demand[-1].reshape(1, -1).expand(h, -1))
    torch.testing.assert_close(first, demand[-1].reshape(-1))
    scorer, first = perfect._scorer(one, demand, fleet)                      # decision at slot 0
    torch.testing.assert_close(scorer.override, true[1:1 + h])
    torch.testing.assert_close(first, true[1])
    perfect.t = true.shape[0] - 3                                            # three slots before the day's end
    scorer, _ = perfect._scorer(one, demand, fleet)
    torch.testing.assert_close(scorer.override[:2], true[-2:])
    torch.testing.assert_close(scorer.override[2:], true[-1:].expand(h - 2, -1))
    # both act through the controller interface
    a = perfect.act(one)
    assert a.shape == (core.scenario.n_uavs, 3) and np.abs(a).max() <= 1.0
