"""HRL-TPRA: the pointer planner's assignments and log-probabilities, the batched per-UAV actors against the
per-actor loop, the inputs and the composed action, the targets at a day's end, training on small synthetic days
(loss, checkpoint resumption, recorded days, seeds), and acting within bounds."""
import dataclasses
import itertools
import math

import numpy as np
import pytest
import torch

from dswm.config import ConfigError
from dswm.methods.hrl_tpra import HRLTPRAController, HRLTPRASettings
from dswm.methods.hrl_tpra.actors import LoopMLP, ResourceActors, StackedMLP
from dswm.methods.hrl_tpra.features import (FAR, Frame, compose_action, local_dim, low_inputs, plan_inputs,
                                            slot_of)
from dswm.methods.hrl_tpra.learner import gae, macro_targets
from dswm.methods.hrl_tpra.pointer import PointerPlanner
from dswm.methods.hrl_tpra.training import Trainer
from dswm.methods.trained import day_schedule
from dswm.sim.core import Grid, build_observation
from dswm.sim.fleet import CHARGING, FleetState
from learner_checks import (DAY_IDS, GRID, check_actions_bounded_and_moves_within_dmax, check_same_seed_same_actions,
                            check_save_load, check_trains_on_training_days_and_evaluates_batched_as_alone, contexts)
from learner_checks import core, scenario3  # noqa: F401 (fixtures)

SMALL = HRLTPRASettings(macro_slots=6, candidates=8, pointer_hidden=16, tanh_clip=10.0, crop_radius=1,
                        actor_hidden=16, actor_depth=2, fine_scale=0.5, log_std_init=-0.5, gamma=0.9,
                        gae_lambda=0.95, high_gamma=0.5, clip_range=0.2, ent_coef=0.0, high_ent_coef=0.01, lr=3e-3,
                        high_lr=1e-3, max_grad_norm=1.0, n_envs=2, day_episodes=12, n_epochs=5, high_epochs=5,
                        batch_size=32, high_batch_size=16, log_points=3, checkpoint_every=2)
QUICK = dataclasses.replace(SMALL, day_episodes=2, n_epochs=1, high_epochs=1, batch_size=143,
                            high_batch_size=48)  # one round of two days


@pytest.fixture(scope="module")
def fitted(core, tmp_path_factory):
    """SMALL trained on the core: (controller, manifest, probe rollout, critic losses on it before training)."""
    probe = Trainer(core=core, settings=SMALL, seed=7)
    rollout, _ = probe.collect(np.array([0, 3]))  # untrained policies: a fixed batch, and untrained critics
    before = (probe.learner.critic_loss(rollout), probe.learner.plan_critic_loss(rollout))
    ctrl = HRLTPRAController(name="hrl_tpra", seed=0, options=SMALL)
    manifest = ctrl.fit(core, run_dir=tmp_path_factory.mktemp("hrl_run"))
    return ctrl, manifest, rollout, before



# ----------------------------------------------------------------------------------- settings

@pytest.mark.parametrize("key,value", [("gamma", 1.0), ("high_gamma", -0.1), ("day_episodes", 13),
                                       ("crop_radius", -1), ("fine_scale", 0.0), ("macro_slots", 0)])
def test_settings_name_the_bad_key(key, value):
    with pytest.raises(ConfigError, match=f"methods.hrl_tpra.{key}"):
        dataclasses.replace(SMALL, **{key: value})


def test_fewer_candidates_than_uavs_is_refused(core, tmp_path):
    ctrl = HRLTPRAController(name="hrl_tpra", seed=0, options=dataclasses.replace(SMALL, candidates=2))
    with pytest.raises(ConfigError, match="methods.hrl_tpra.candidates.*at least n_uavs = 3"):
        ctrl.fit(core, run_dir=tmp_path)


# ----------------------------------------------------------------------------------- the pointer planner

def pointer_inputs(b, n, k, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(b, n, 6, generator=g), torch.rand(b, k, 7, generator=g), 3 * torch.rand(b, k, n, generator=g)


def test_pointer_assigns_distinct_cells_with_the_log_probs_it_scores():
    torch.manual_seed(0)
    planner = PointerPlanner(n_uavs=5, hidden=16, tanh_clip=10.0)
    cand, uav, dist = pointer_inputs(64, 7, 5)
    plan = planner(cand, uav, dist, generator=torch.Generator().manual_seed(1))
    assert plan.choice.shape == (64, 5) and plan.choice.dtype == torch.int64
    assert all(len(set(row)) == 5 for row in plan.choice.tolist())  # no cell twice
    assert int(plan.choice.min()) >= 0 and int(plan.choice.max()) < 7
    assert bool((plan.logp < 0).all()) and bool(torch.isfinite(plan.logp).all())
    scored = planner(cand, uav, dist, choice=plan.choice)  # teacher forcing gives the same log-probabilities
    torch.testing.assert_close(scored.logp, plan.logp)
    torch.testing.assert_close(scored.entropy, plan.entropy)
    greedy = planner(cand, uav, dist, greedy=True)
    assert bool((greedy.logp >= plan.logp - 1e-6).float().mean() > 0.9)  # greedy paths are the likely ones


def test_pointer_probabilities_of_all_assignments_sum_to_one():
    torch.manual_seed(1)
    planner = PointerPlanner(n_uavs=3, hidden=8, tanh_clip=2.0)
    cand, uav, dist = pointer_inputs(2, 4, 3, seed=3)
    perms = torch.tensor(list(itertools.permutations(range(4), 3)))  # the 24 ordered selections of 3 of 4 cells
    total = torch.zeros(2)
    first = torch.zeros(2, 4)
    for p in perms:
        with torch.no_grad():
            prob = planner(cand, uav, dist, choice=p.expand(2, 3)).logp.exp()
        total += prob
        first[:, p[0]] += prob
    torch.testing.assert_close(total, torch.ones(2))
    # the first UAV's marginal is a proper distribution whose entropy is the first term of the plan's entropy
    one = PointerPlanner(n_uavs=3, hidden=8, tanh_clip=2.0)
    one.load_state_dict(planner.state_dict())
    with torch.no_grad():
        ent = one(cand, uav[:, :1], dist[:, :1], greedy=True).entropy
    torch.testing.assert_close(ent, -(first * first.log()).sum(-1))
    assert float(first.min()) > 0.01  # C = 2 keeps every cell possible


def test_pointer_refuses_fewer_candidates_than_uavs():
    planner = PointerPlanner(n_uavs=3, hidden=8, tanh_clip=10.0)
    with pytest.raises(ValueError, match="2 candidates for 3 UAVs"):
        planner(*pointer_inputs(1, 2, 3))


# ----------------------------------------------------------------------------------- batched actors

def test_batched_actors_compute_what_the_per_actor_loop_computes():
    torch.manual_seed(0)
    stacked = StackedMLP(n=4, sizes=[9, 16, 16, 3], out_gain=0.5)
    loop = LoopMLP.from_stacked(stacked)
    x = torch.randn(4, 11, 9)
    y_stacked, y_loop = stacked(x), loop(x)
    assert y_stacked.shape == (4, 11, 3)
    torch.testing.assert_close(y_stacked, y_loop, rtol=1e-6, atol=1e-6)
    # the same gradients for every UAV's own weights
    y_stacked.pow(2).sum().backward()
    y_loop.pow(2).sum().backward()
    for k, net in enumerate(loop.nets):
        linears = [m for m in net if isinstance(m, torch.nn.Linear)]
        for lin, w, b in zip(linears, stacked.weights, stacked.biases, strict=True):
            torch.testing.assert_close(w.grad[k].T, lin.weight.grad, rtol=1e-5, atol=1e-6)
            torch.testing.assert_close(b.grad[k, 0], lin.bias.grad, rtol=1e-5, atol=1e-6)
    # separate weights, not a shared network: one input through the four UAVs gives four outputs
    with torch.no_grad():
        same = stacked(torch.randn(1, 5, 9).expand(4, 5, 9))
    assert float((same[0] - same[1]).abs().max()) > 1e-3


def test_resource_actors_log_prob_is_the_gaussian_density():
    torch.manual_seed(0)
    actors = ResourceActors(n_uavs=3, in_dim=local_dim(1), hidden=8, depth=1, log_std_init=-0.5)
    mean, action = torch.randn(5, 3, 3), torch.randn(5, 3, 3)
    dist = torch.distributions.Normal(mean, actors.log_std.exp().detach())
    torch.testing.assert_close(actors.log_prob(mean, action), dist.log_prob(action).sum(-1))
    torch.testing.assert_close(actors.entropy(), dist.entropy()[0].sum(-1))


# ----------------------------------------------------------------------------------- inputs and action

def test_planner_sees_the_top_cells_of_the_current_map(scenario3):
    frame = Frame.of(GRID, scenario3)
    demand = torch.zeros(1, 7, 6, 6)
    demand[0, -1].view(-1)[torch.tensor([3, 20, 35, 8])] = torch.tensor([4.0, 9.0, 1.0, 2.0])
    demand[0, 0].view(-1)[20] = 9.0  # older maps do not rank the candidates
    fleet = torch.zeros(1, 3, 7)
    fleet[0, :, :2] = torch.tensor([[0.5, 0.5], [0.1, 0.1], [0.9, 0.9]])
    fleet[0, :2, 3] = 1.0  # UAV 2 is charging
    fleet[0, 2, 5] = 1.0
    plan = plan_inputs(demand, fleet, torch.zeros(1, 2), frame, 4)
    assert plan.cells[0].tolist() == [20, 3, 8, 35]
    torch.testing.assert_close(plan.cand[0, :, 2], torch.log1p(torch.tensor([9.0, 4.0, 2.0, 1.0])))
    torch.testing.assert_close(plan.cand[0, 0, 4], torch.tensor(0.0))  # no trend at cell 20: 9 then 9
    centre = frame.cells[plan.cells[0]]
    pos = frame.positions(fleet[0])
    want = (torch.cdist(pos, centre) / scenario3.d_max_m).clamp(max=FAR)
    torch.testing.assert_close(plan.dist[0], want)
    torch.testing.assert_close(plan.cand[0, :, 5], want[:2].min(0).values)  # nearest ACTIVE UAV only


def test_resource_actor_input_crops_demand_and_counts_the_other_active_uavs(scenario3):
    frame = Frame.of(GRID, scenario3)
    demand = torch.zeros(1, 7, 6, 6)
    demand[0, -1] = torch.arange(36, dtype=torch.float32).view(6, 6)
    fleet = torch.zeros(1, 3, 7)
    fleet[0, :, 0] = torch.tensor([0.5, 1.5, 1.5]) / 6  # UAV 0 in cell (0, 0), UAVs 1 and 2 in cell (1, 1)
    fleet[0, :, 1] = torch.tensor([0.5, 1.5, 1.5]) / 6
    fleet[0, :2, 3] = 1.0  # UAV 2 is charging
    target = torch.tensor([[14, 0, 35]])
    local, glob = low_inputs(demand, fleet, torch.tensor([[0.5, -0.5]]), target, torch.tensor([0.5]), frame, 1)
    assert local.shape == (1, 3, local_dim(1)) == (1, 3, 32)
    crop = local[0, :, 11:29].reshape(3, 2, 3, 3)
    log1p = torch.log1p(torch.tensor([[0.0, 0, 0], [0, 0, 1], [0, 6, 7]]))  # zero outside the area (south-west)
    torch.testing.assert_close(crop[0, 0], log1p)
    assert crop[0, 1].tolist() == [[0, 0, 0], [0, 0, 0], [0, 0, 1]]  # UAV 1 at its north-east, not itself
    assert crop[1, 1].tolist() == [[1, 0, 0], [0, 0, 0], [0, 0, 0]]  # UAV 2 is not active: not counted
    offset = (frame.cells[14] - frame.positions(fleet[0, 0])) / scenario3.d_max_m
    torch.testing.assert_close(local[0, 0, 7:9], offset)
    assert float(local[0, 0, 10]) == pytest.approx(math.log1p(14.0))
    torch.testing.assert_close(local[0, 0, -3:], torch.tensor([0.5, -0.5, 0.5]))
    torch.testing.assert_close(glob[0], torch.tensor([torch.log1p(torch.arange(36.0)).mean(), 2 / 3]))


def test_composed_action_flies_to_a_near_target_and_respects_dmax(scenario3):
    big = Grid(rows=20, cols=20, cell_m=235.0)
    frame = Frame.of(big, scenario3)
    fleet = torch.zeros(1, 3, 7)
    fleet[0, :, :2] = torch.tensor([[0.5, 0.5], [0.5, 0.5], [0.02, 0.02]])
    target = torch.tensor([[7 * 20 + 12, 0, 399]])  # near (~1.1 km), far (~3.3 km), far (~6.3 km)
    zero = compose_action(torch.zeros(1, 3, 3), fleet, target, frame, 0.5)
    pos = frame.positions(fleet[0])
    torch.testing.assert_close(pos[0] + zero[0, 0, :2] * scenario3.d_max_m, frame.cells[target[0, 0]])
    assert float(zero[0, 1, :2].norm()) == pytest.approx(1.0, abs=1e-6)  # full D_max towards a far target
    g = torch.Generator().manual_seed(0)
    out = torch.rand(500, 3, 3, generator=g) * 2 - 1
    act = compose_action(out, fleet.expand(500, 3, 7), target.expand(500, 3), frame, 0.5)
    assert float(act.abs().max()) <= 1.0
    torch.testing.assert_close(act[..., 2], out[..., 2])
    assert float((act[..., :2] - zero[..., :2]).abs().max()) <= 0.5 + 1e-6  # the fine move is a correction


def test_slot_is_read_back_from_the_time_phase(scenario3):
    slots = torch.arange(144)
    time = torch.as_tensor(build_observation(
        torch.zeros(144, 7, 2, 2), FleetState(torch.zeros(144, 3, 2), torch.ones(144, 3),
                                              torch.full((144, 3), CHARGING), torch.zeros(144, 3, dtype=torch.long)),
        slots, Grid(rows=2, cols=2, cell_m=1.0), scenario3)["time"])
    assert torch.equal(slot_of(time, 144), slots)


# ----------------------------------------------------------------------------------- targets

def test_gae_bootstraps_at_the_days_end_and_stops_on_termination():
    reward = torch.tensor([[1.0, 1.0], [0.5, 2.0], [0.0, -1.0]])  # (T=3, E=2)
    value = torch.tensor([[[0.2], [0.1]], [[0.4], [-0.3]], [[0.6], [0.5]]])  # (T, E, K=1)
    last = torch.tensor([[2.0], [3.0]])
    term = torch.tensor([[False, False], [False, False], [False, True]])  # day 1's last step terminates
    g = 0.9
    adv, target = gae(reward, value, last, term, g, 0.0)  # lambda 0: one-step TD targets
    want = torch.tensor([[1.0 + g * 0.4, 1.0 + g * -0.3], [0.5 + g * 0.6, 2.0 + g * 0.5],
                         [0.0 + g * 2.0, -1.0]]).unsqueeze(-1)  # day 0 truncated: + gamma V(o_T)
    torch.testing.assert_close(target, want)
    torch.testing.assert_close(adv, want - value)
    _, mc = gae(reward, value, last, term, g, 1.0)  # lambda 1: discounted returns plus the bootstrap
    torch.testing.assert_close(mc[0, 0, 0], torch.tensor(1.0 + g * 0.5 + g * g * (0.0 + g * 2.0)))
    torch.testing.assert_close(mc[0, 1, 0], torch.tensor(1.0 + g * 2.0 + g * g * -1.0))


def test_macro_targets_bootstrap_on_the_next_macro_slot_and_the_days_last_observation():
    reward = torch.tensor([[3.0], [-1.0]])
    value = torch.tensor([[0.5], [1.5]])
    adv, target = macro_targets(reward, value, torch.tensor([4.0]), torch.zeros(2, 1, dtype=torch.bool), 0.5)
    torch.testing.assert_close(target, torch.tensor([[3.0 + 0.5 * 1.5], [-1.0 + 0.5 * 4.0]]))
    torch.testing.assert_close(adv, target - value)
    _, plain = macro_targets(reward, value, torch.tensor([4.0]), torch.zeros(2, 1, dtype=torch.bool), 0.0)
    torch.testing.assert_close(plain, reward)  # high_gamma 0: the macro-slot's summed reward


def test_rollout_holds_whole_days_and_macro_rewards_sum_the_slots(core):
    trainer = Trainer(core=core, settings=QUICK, seed=0)
    ro, sr = trainer.collect(np.array([1, 2]))
    assert ro.reward.shape == (143, 2) and ro.local.shape == (143, 2, 3, local_dim(1))
    assert ro.choice.shape == (24, 2, 3) and ro.last_value.shape == (2, 3) and ro.plan_last_value.shape == (2,)
    torch.testing.assert_close(ro.macro_reward[:-1], ro.reward[:138].view(23, 6, 2).sum(1))
    torch.testing.assert_close(ro.macro_reward[-1], ro.reward[138:].sum(0))  # the last macro-slot: 5 slots
    assert sr.shape == (2,) and bool(((sr > 0) & (sr <= 1)).all())


# ----------------------------------------------------------------------------------- training

def test_training_lowers_the_critic_losses_on_a_fixed_rollout(fitted):
    ctrl, manifest, rollout, (low_before, high_before) = fitted
    assert manifest["steps"] >= 300
    low_after, high_after = ctrl.learner.critic_loss(rollout), ctrl.learner.plan_critic_loss(rollout)
    assert low_after < 0.3 * low_before, (low_before, low_after)
    assert high_after < 0.5 * high_before, (high_before, high_after)
    history = manifest["history"]
    assert history["losses/value"][-1] < 0.5 * history["losses/value"][0]


def test_manifest_records_exactly_the_training_days_used(fitted, core):
    ctrl, manifest, _, _ = fitted
    schedule = day_schedule(core.n_days, SMALL.day_episodes, 0)
    assert manifest["days"] == [int(DAY_IDS[d]) for d in schedule]
    assert set(manifest["days"]) <= set(DAY_IDS.tolist())
    assert manifest["day_labels"] == [core.day_labels[d] for d in schedule]
    assert manifest["transitions_per_day_episode"] == 143
    assert manifest["n_transitions"] == 143 * len(manifest["days"]) == 143 * SMALL.day_episodes
    assert manifest["read_test_data"] is False
    blob = torch.load(manifest["checkpoint"], weights_only=False)
    assert [int(DAY_IDS[d]) for d in blob["days_used"]] == manifest["days"]
    history = manifest["history"]
    assert history["step"] == [572, 1144, 1716] and all(len(v) == 3 for v in history.values())


def test_checkpoint_resumes_to_identical_next_round(core, tmp_path):
    settings = dataclasses.replace(QUICK, day_episodes=4, n_epochs=2, high_epochs=2, batch_size=100)
    a = Trainer(core=core, settings=settings, seed=4)
    a.run_round()
    a.save(tmp_path / "ckpt.pt", {"run": 1})
    want = a.run_round()
    b = Trainer(core=core, settings=settings, seed=4)
    torch.manual_seed(123)  # the global RNG moves on: the checkpoint must bring everything back
    b.restore(torch.load(tmp_path / "ckpt.pt", weights_only=False))
    got = b.run_round()
    assert got == want  # the days, the return, the served ratio and every mean loss, exactly
    assert a.learner.steps == b.learner.steps == 2 * (2 * 3 + 2)
    for p, q in zip(a.learner.actors.parameters(), b.learner.actors.parameters(), strict=True):
        assert torch.equal(p, q)
    for p, q in zip(a.learner.planner.parameters(), b.learner.planner.parameters(), strict=True):
        assert torch.equal(p, q)


def test_fit_continues_a_finished_run_from_its_checkpoint(core, tmp_path, monkeypatch):
    first = HRLTPRAController(name="hrl_tpra", seed=1, options=QUICK).fit(core, run_dir=tmp_path)

    def no_round(self):
        raise AssertionError("a finished run was trained again")

    monkeypatch.setattr(Trainer, "run_round", no_round)
    again = HRLTPRAController(name="hrl_tpra", seed=1, options=QUICK)
    second = again.fit(core, run_dir=tmp_path)
    assert second["days"] == first["days"]
    assert second["steps"] == first["steps"] == 3  # two actor minibatches and one planner step
    assert second["history"] == first["history"]
    obs = core.reset([0])
    again.reset_batch(contexts(core, [0]))
    assert np.all(np.isfinite(again.act_batch(obs)))  # the restored networks act
    other = HRLTPRAController(name="hrl_tpra", seed=2, options=QUICK)  # another seed does not take the checkpoint
    with pytest.raises(AssertionError, match="trained again"):
        other.fit(core, run_dir=tmp_path)


# ----------------------------------------------------------------------------------- acting

def make(seed, options):
    return HRLTPRAController(name="hrl_tpra", seed=seed, options=options)


def test_actions_are_bounded_and_moves_stay_within_dmax(fitted, core):
    moved = check_actions_bounded_and_moves_within_dmax(fitted[0], core)
    assert moved > 0.1 * core.scenario.d_max_m  # the policy does move the fleet


def test_same_seed_same_actions(core, tmp_path):
    check_same_seed_same_actions(make, QUICK, core, tmp_path)


def test_save_load_round_trip_and_checks(fitted, core, tmp_path):
    # 8 slots: across a macro-slot boundary
    check_save_load(fitted[0], make, SMALL, dataclasses.replace(SMALL, actor_hidden=8), core, tmp_path, slots=8)


def test_trains_on_the_training_days_of_a_tensor_and_evaluates_batched_as_alone(scenario3, tmp_path):
    options = dataclasses.replace(QUICK, n_envs=3, day_episodes=3)
    check_trains_on_training_days_and_evaluates_batched_as_alone(make, options, scenario3, tmp_path)
