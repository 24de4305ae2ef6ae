"""Observation-anchored CEM planner: CEM core, anchoring arithmetic, scorer plumbing, and the agreement of
imagination with the environment when the true demand is supplied."""

import dataclasses

import numpy as np
import pytest
import torch

from dswm.methods.search import SearchSettings

from dswm.sim.core import FleetCore, Grid, fleet_state_from_obs
from dswm.sim.env import synthetic_demand
from dswm.sim.fleet import ACTIVE, CHARGING, RETURNING, available, fleet_step
from dswm.sim.physics import ServiceParams, served_ratio
from dswm.methods.dswm.planner import (AnchoredCEMPlanner, ImaginationScorer, ImaginedWorld, PlannerConfig, StepScoring,
                                       anchor, cem)
from dswm.methods.dswm.rssm import RSSMConfig
from dswm.methods.dswm.modules import symlog
from dswm.methods.dswm.world_model import WorldModel, WorldModelConfig


def test_cem_finds_known_optimum():
    torch.manual_seed(0)
    target = torch.rand(3, 2, 3) * 1.6 - 0.8             # interior optimum in (-0.8, 0.8)
    target[0, 0, 0] = 1.0                                  # and one coordinate on the boundary

    def score(a):
        return -((a - target) ** 2).flatten(1).sum(-1)

    res = cem(score, mean=torch.zeros(3, 2, 3), std=torch.full((3, 2, 3), 0.5), n_samples=256, n_elites=32,
              iterations=12, min_std=0.01, generator=torch.Generator().manual_seed(1))
    assert float((res.best - target).abs().max()) < 0.05
    assert res.scores == sorted(res.scores)               # the best so far never gets lost


def test_cem_seed_sequence_is_kept_when_it_is_best():
    target = torch.full((2, 1, 3), 0.7)
    res = cem(lambda a: -((a - target) ** 2).flatten(1).sum(-1), mean=torch.zeros(2, 1, 3),
              std=torch.full((2, 1, 3), 0.01), n_samples=16, n_elites=4, iterations=2, min_std=0.01,
              generator=torch.Generator().manual_seed(0), seeds=target.unsqueeze(0))
    assert res.best_score == 0.0 and torch.equal(res.best, target)


def test_anchor_arithmetic():
    x_now = torch.tensor([1.0, 2.0])
    members = torch.tensor([[[3.0, 0.0]], [[5.0, 4.0]]])  # (E=2, N=1, G=2)
    x_hat, u = anchor(x_now, members, 0.9)
    # heads after anchoring: [1.2, 1.8] and [1.4, 2.2]; mean [1.3, 2.0]; population std [0.1, 0.2]
    torch.testing.assert_close(x_hat, torch.tensor([[1.3, 2.0]]))
    assert abs(float(u[0]) - 0.3 / 3.3) < 1e-6


def _grid_setup(scenario, rows=6, cols=6):
    grid = Grid(rows=rows, cols=cols, cell_m=500.0)
    return grid, grid.geometry(), grid.cells(), ServiceParams.from_scenario(scenario)


def _constant_head_model(scenario, grid, cells, params, maps):
    """A world model whose E heads output fixed maps (E, G) whatever the latent state."""
    cfg = WorldModelConfig(rssm=RSSMConfig(deter=16, stoch=4, hidden=16, embed=16, min_std=0.1,
                                           free_bits=0.1, kl_dyn=0.8, kl_rep=0.2),
                           ensemble=maps.shape[0], demand_hidden=8, demand_rank=4, enc_channels=4, head_hidden=16,
                           ema_nu=0.9, lambda_var=1.0, m_var=0.1, beta_kl=1.0, lambda_lpr=1.0, lambda_cal=0.1,
                           lambda_serve=1.0, service_head="physics")
    model = WorldModel(cfg=cfg, rows=grid.rows, cols=grid.cols, n_uavs=scenario.n_uavs, window=7, cells=cells,
                       params=params)
    with torch.no_grad():
        model.demand.w2.zero_()
        model.demand.b2.zero_()
        model.demand.bias.copy_(symlog(maps))
    return model


def test_scorer_rolls_fleet_and_scores_anchored_demand(scenario):
    torch.manual_seed(0)
    grid, geom, cells, params = _grid_setup(scenario)
    g, k = grid.n_cells, scenario.n_uavs
    maps = torch.rand(3, g) * 2.0
    model = _constant_head_model(scenario, grid, cells, params, maps)
    x_now = torch.rand(g)
    fleet0 = fleet_state_from_obs(np.concatenate([np.random.default_rng(0).uniform(0, 1, (k, 2)),
                                                  np.full((k, 1), 0.3), np.tile([[1, 0, 0, 0]], (k, 1))], 1),
                                  grid, scenario)
    actions = torch.rand(4, 5, k, 3) * 2 - 1              # N=4 candidates, H=5
    gamma, rho, lam = 0.9, 0.95, 1.0
    scorer = ImaginationScorer(model=model, latent=model.rssm.initial(1), fleet=fleet0, x_now=x_now,
                               world=ImaginedWorld(cells=cells, geom=geom, scenario=scenario, params=params),
                               scoring=StepScoring(rho=rho, lambda_u=lam, continuation="hold"), gamma=gamma,
                               compile=False)
    got = scorer(actions)
    # independent computation: anchored mean map and relative spread are the same at every step
    heads = rho * x_now + (1 - rho) * maps                  # (E, G)
    x_hat = heads.mean(0)
    u = float(heads.std(0, unbiased=False).sum() / x_hat.sum())
    for n in range(4):
        state, ref = fleet0, 0.0
        for tau in range(5):
            state, _ = fleet_step(state, actions[n, tau], geom, scenario)
            sr = served_ratio(x_hat, state.pos[None], available(state)[None], cells, params=params,
                              bw_logit=actions[n, tau, :, 2][None])
            ref += gamma ** (tau + 1) * (float(sr[0]) - lam * u)
        assert abs(float(got[n]) - ref) < 1e-5


@pytest.mark.parametrize("continuation", ["hold", "lloyd"])
def test_imagination_agrees_with_environment_including_battery_returns(scenario, continuation):
    grid, geom, cells, params = _grid_setup(scenario)
    demand = synthetic_demand(days=1, rows=grid.rows, cols=grid.cols, seed=3) + 0.05
    init = np.random.default_rng(1).uniform(500, 2500, (scenario.n_uavs, 2)).astype(np.float32)
    core = FleetCore(demand=demand, grid=grid, scenario=scenario, init_pos=init, dataset="agree",
                     day_labels=["d0"])
    obs = core.reset([0])
    rng = np.random.default_rng(2)
    for _ in range(3):                                     # move away from slot 0 first
        obs = core.step(rng.uniform(-1, 1, (1, scenario.n_uavs, 3)).astype(np.float32)).obs
    t0, horizon, gamma = core.t, 15, 0.93
    actions = torch.as_tensor(rng.uniform(-1, 1, (horizon, scenario.n_uavs, 3)).astype(np.float32))
    truth = torch.as_tensor(demand[0, t0 + 1:t0 + 1 + horizon].reshape(horizon, -1))
    fleet = fleet_state_from_obs(obs["fleet"][0], grid, scenario)
    scorer = ImaginationScorer(model=None, latent=None, fleet=fleet, x_now=truth[0],
                               world=ImaginedWorld(cells=cells, geom=geom, scenario=scenario, params=params),
                               scoring=StepScoring(rho=0.95, lambda_u=1.0, continuation=continuation), gamma=gamma,
                               compile=False, demand_override=truth)
    imagined = float(scorer(actions.unsqueeze(0))[0])
    taken = scorer.last_actions[0]                         # the sequence with the continuation applied
    assert torch.equal(taken[0], actions[0])               # the executed first action is the sampled one
    if continuation == "lloyd":
        assert float((taken[1:] - actions[1:]).abs().max()) > 0.01
    realized, statuses = 0.0, []
    for tau in range(horizon):
        out = core.step(taken[tau].numpy()[None])
        realized += gamma ** (tau + 1) * float(out.sr[0])
        statuses.append(core.state.status[0].clone())
    statuses = torch.stack(statuses)
    assert bool((statuses == RETURNING).any())              # battery returns happen inside the horizon
    back = (statuses[:-1] == CHARGING) & (statuses[1:] == ACTIVE)
    assert bool(back.any())                                 # and a UAV comes back from charging
    assert abs(imagined - realized) < 1e-5
    assert realized > 1.0                                  # a non-trivial score, sum of 15 discounted SRs


def test_planner_warm_start_and_reproducibility(scenario):
    cfg = PlannerConfig(horizon=4, n_samples=32, n_elites=4, iterations=2, sigma0=0.3, sigma0_later=0.3,
                        min_std=0.05, gamma=0.9, rho=0.95, lambda_u=1.0, warm_start=True, carry_best=True,
                        continuation="hold", proposal="none",
                        search=SearchSettings(sweeps=1, lattice=3, refine=0, bw_logits=(0.0,)), compile=False)
    target = torch.full((4, scenario.n_uavs, 3), 0.4)

    def score(a):
        return -((a - target) ** 2).flatten(1).sum(-1)

    p1 = AnchoredCEMPlanner(cfg=cfg, n_uavs=scenario.n_uavs, device="cpu", seed=5)
    a1, r1 = p1.plan(score)
    p2 = AnchoredCEMPlanner(cfg=cfg, n_uavs=scenario.n_uavs, device="cpu", seed=5)
    b1, _ = p2.plan(score)
    assert torch.equal(a1, b1)                             # same seed, same plan
    p2.reset(0)
    c1, _ = p2.plan(score)
    assert torch.equal(a1, c1)                             # reset restores the day's random stream
    # Warm start: the next slot's population holds the previous best shifted by one step (last step 0).
    shifted = torch.cat([r1.best[1:], torch.zeros_like(r1.best[:1])])
    _, r2 = p1.plan(lambda a: -((a - shifted) ** 2).flatten(1).sum(-1))
    assert r2.best_score == 0.0 and torch.equal(r2.best, shifted)
    assert tuple(p1.prev_mean.shape) == (4, scenario.n_uavs, 3)


@pytest.mark.parametrize("use_model", [True, False])
def test_compiled_imagination_matches_the_eager_one(scenario, use_model):
    """``planner.compile`` runs the same imagined step through torch.compile: same scores, same taken actions."""
    torch.manual_seed(0)
    grid, geom, cells, params = _grid_setup(scenario)
    g, k, horizon = grid.n_cells, scenario.n_uavs, 4
    model = _constant_head_model(scenario, grid, cells, params, torch.rand(3, g) * 2.0)
    with torch.no_grad():                                 # heads that depend on the imagined latent state
        model.demand.w2.normal_(0.0, 0.5)
    rng = np.random.default_rng(5)
    fleet = fleet_state_from_obs(np.concatenate([rng.uniform(0, 1, (k, 2)), rng.uniform(0.2, 1.0, (k, 1)),
                                                 np.tile([[1, 0, 0, 0]], (k, 1))], 1), grid, scenario)
    truth = torch.rand(horizon, g) * 3.0
    actions = torch.rand(8, horizon, k, 3) * 2 - 1
    common = dict(model=model if use_model else None, latent=model.rssm.initial(1) if use_model else None,
                  fleet=fleet, x_now=torch.rand(g),
                  world=ImaginedWorld(cells=cells, geom=geom, scenario=scenario, params=params),
                  scoring=StepScoring(rho=0.9, lambda_u=1.0, continuation="lloyd"), gamma=0.9,
                  demand_override=None if use_model else truth)
    eager, compiled = ImaginationScorer(**common, compile=False), ImaginationScorer(**common, compile=True)
    want = eager(actions)
    graphs = torch._dynamo.utils.counters["stats"]["unique_graphs"]
    got = compiled(actions)
    assert torch._dynamo.utils.counters["stats"]["unique_graphs"] - graphs == 2   # first step, later steps
    assert float(want.abs().min()) > 0.1                  # non-trivial scores
    torch.testing.assert_close(got, want, rtol=0, atol=1e-5)
    torch.testing.assert_close(compiled.last_actions, eager.last_actions, rtol=0, atol=1e-5)


def test_algorithm_1_forgets_each_slot_and_plain_cem_does_not_re_enter_its_best(scenario):
    """Without warm start the next slot plans exactly as a fresh planner; carry_best re-enters the best sequence
    into the next iteration's population, plain CEM (Algorithm 1) does not."""
    base = dict(horizon=3, n_samples=16, n_elites=4, iterations=2, sigma0=0.3, sigma0_later=None, min_std=0.0,
                gamma=0.9, rho=0.95, lambda_u=1.0, continuation="hold", proposal="none",
                search=SearchSettings(sweeps=1, lattice=3, refine=0, bw_logits=()), compile=False)
    alg1 = PlannerConfig(**base, warm_start=False, carry_best=False)
    target = torch.full((3, scenario.n_uavs, 3), 0.4)
    seen = []

    def score(a):
        seen.append(a.clone())
        return -((a - target) ** 2).flatten(1).sum(-1)

    p = AnchoredCEMPlanner(cfg=alg1, n_uavs=scenario.n_uavs, device="cpu", seed=2)
    first, r1 = p.plan(score)
    p.reset(0)
    again, _ = p.plan(score)
    assert torch.equal(first, again) and torch.equal(p.warm_mean(), torch.zeros_like(p.warm_mean()))
    # iteration 2's population never holds iteration 1's best (sampled afresh) ...
    best1 = seen[0][torch.argmax(score(seen[0]))]
    assert not any(torch.equal(c, best1) for c in seen[1])
    # ... while with carry_best it is the population's first member
    seen.clear()
    q = AnchoredCEMPlanner(cfg=PlannerConfig(**base, warm_start=False, carry_best=True), n_uavs=scenario.n_uavs,
                           device="cpu", seed=2)
    q.plan(score)
    best1 = seen[0][torch.argmax(score(seen[0]))]
    assert torch.equal(seen[1][0], best1)
    assert alg1.later_std == 0.3 and dataclasses.replace(alg1, sigma0_later=0.05).later_std == 0.05
