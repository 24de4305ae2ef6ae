"""MADDPG: local observations, the centralized critic's actor objective, the TD target at a day's end, training
on small synthetic days (loss, cross-agent spread, checkpoint resumption, recorded days, seeds), acting within
bounds, and the PettingZoo parallel environment it trains through."""
import dataclasses

import numpy as np
import pytest
import torch
from pettingzoo.test import parallel_api_test

from dswm.config import ConfigError
from dswm.methods.maddpg import MADDPGController, MADDPGSettings
from dswm.methods.maddpg.learner import Inputs, Learner
from dswm.methods.maddpg.networks import (HEAD_INIT, CentralCritic, SharedActor, agent_spread, joint_observation,
                                          local_dim, local_observation, scale_demand)
from dswm.methods.maddpg.replay import window_maps
from dswm.methods.maddpg.training import Trainer, parallel_env
from dswm.methods.trained import day_schedule
from learner_checks import (DAY_IDS, check_actions_bounded_and_moves_within_dmax, check_same_seed_same_actions,
                            check_save_load, check_trains_on_training_days_and_evaluates_batched_as_alone)
from learner_checks import core, scenario3  # noqa: F401 (fixtures)

SMALL = MADDPGSettings(crop_radius=1, index_embed=4, actor_hidden=16, actor_depth=2, critic_hidden=32, critic_depth=2,
                       actor_lr=1e-3, critic_lr=1e-3, gamma=0.5, tau=0.05, noise_std=0.2, action_reg=1e-3,
                       grad_clip=1.0, buffer_size=1000, batch_size=32, warmup=100, transitions=2 * 143,
                       update_every=1, gradient_steps=2, log_points=10, checkpoint_every=1, matmul_dtype="float32")
QUICK = dataclasses.replace(SMALL, transitions=143, gradient_steps=1)  # one day-episode, 44 gradient steps


@pytest.fixture(scope="module")
def fitted(core, tmp_path_factory):
    """SMALL trained on the core: (controller, manifest, loss on a fixed batch before training, that batch)."""
    probe = Trainer(core=core, settings=dataclasses.replace(SMALL, warmup=10 ** 6), seed=0)
    probe.run_episode()  # random actions, no gradient step: a fixed batch, and the untrained networks
    batch = probe.learner.inputs(probe.replay.take(torch.arange(143)), probe.maps)
    with torch.no_grad():
        before = float(probe.learner.critic_loss(batch))
    ctrl = MADDPGController(name="maddpg", seed=0, options=SMALL)
    manifest = ctrl.fit(core, run_dir=tmp_path_factory.mktemp("maddpg_run"))
    return ctrl, manifest, before, batch



# ----------------------------------------------------------------------------------- settings and networks

@pytest.mark.parametrize("key,value", [("gamma", 1.0), ("tau", 0.0), ("batch_size", 2000), ("crop_radius", -1),
                                       ("noise_std", -0.1), ("update_every", 0)])
def test_settings_name_the_bad_key(key, value):
    with pytest.raises(ConfigError, match=f"methods.maddpg.{key}"):
        dataclasses.replace(SMALL, **{key: value})


def test_transitions_must_be_whole_days(core, tmp_path):
    ctrl = MADDPGController(name="maddpg", seed=0, options=dataclasses.replace(SMALL, transitions=200))
    with pytest.raises(ConfigError, match="methods.maddpg.transitions.*multiple of 143"):
        ctrl.fit(core, run_dir=tmp_path)


def test_local_observation_crops_around_the_uav_and_counts_the_others():
    rows, cols, r = 4, 5, 1
    maps = torch.arange(2 * rows * cols, dtype=torch.float32).reshape(1, 2, rows, cols)  # 2 maps, values = index
    # UAV 0 in cell (row 0, col 0), UAV 1 in cell (1, 1), UAV 2 in cell (1, 1) but charging (not active)
    fleet = torch.zeros(1, 3, 7)
    fleet[0, :, 0] = torch.tensor([0.5, 1.5, 1.5]) / cols
    fleet[0, :, 1] = torch.tensor([0.5, 1.5, 1.5]) / rows
    fleet[0, :, 3] = torch.tensor([1.0, 1.0, 0.0])
    fleet[0, 2, 5] = 1.0
    time = torch.tensor([[0.25, -0.5]])
    out = local_observation(maps, fleet, time, r)
    assert out.shape == (1, 3, local_dim(2, r)) == (1, 3, 3 * 9 + 9)
    crop = out[0, :, :27].reshape(3, 3, 3, 3).permute(0, 3, 1, 2)  # (agent, row, col, channel) -> channel first
    # UAV 0 at the south-west corner: row -1 and col -1 are outside (zeros); map 0 rows 0..1, cols 0..1
    assert crop[0, 0].tolist() == [[0, 0, 0], [0, 0, 1], [0, 5, 6]]
    assert crop[0, 1].tolist() == [[0, 0, 0], [0, 20, 21], [0, 25, 26]]
    # occupancy: UAV 0 sees UAV 1 at its north-east neighbour and not itself; UAV 2 is not active
    assert crop[0, 2].tolist() == [[0, 0, 0], [0, 0, 0], [0, 0, 1]]
    assert crop[1, 2].tolist() == [[1, 0, 0], [0, 0, 0], [0, 0, 0]]
    assert crop[2, 2].tolist() == [[1, 0, 0], [0, 1, 0], [0, 0, 0]]  # UAV 2 is inactive: it removes nothing
    assert crop[1, 0].tolist() == [[0, 1, 2], [5, 6, 7], [10, 11, 12]]
    torch.testing.assert_close(out[0, :, 27:34], fleet[0])
    torch.testing.assert_close(out[0, :, 34:], time.expand(3, 2))


def test_demand_is_scaled_by_log1p_for_both_networks():
    demand = torch.tensor([0.0, 1.0, 9.0]).reshape(1, 1, 1, 3)
    want = torch.tensor([0.0, np.log(2.0), np.log(10.0)], dtype=torch.float32)
    torch.testing.assert_close(scale_demand(demand).flatten(), want)
    joint = joint_observation(scale_demand(demand), torch.zeros(1, 2, 7), torch.ones(1, 2))
    assert joint.shape == (1, 3 + 14 + 2)
    assert float(joint[0, 2]) == pytest.approx(np.log(10.0))


def test_substituted_q_replaces_exactly_one_agents_action():
    torch.manual_seed(0)
    critic = CentralCritic(obs_dim=10, n_agents=4, hidden=16, depth=2)
    x, a, new = torch.randn(5, 10), torch.rand(5, 4, 3) * 2 - 1, torch.rand(5, 4, 3) * 2 - 1
    q = critic.substituted(x, a, new)
    for i in range(4):
        ai = a.clone()
        ai[:, i] = new[:, i]
        torch.testing.assert_close(q[:, i], critic(x, ai))
    assert not torch.allclose(q[:, 0], critic(x, a))


def indexed_local_observation(maps, fleet, time, radius):
    """The local observation by advanced indexing of the permuted padded maps (the reference of the windows)."""
    n, _, rows, cols = maps.shape
    k, side = fleet.shape[1], 2 * radius + 1
    col = torch.clamp((fleet[..., 0] * cols).floor().long(), 0, cols - 1)
    row = torch.clamp((fleet[..., 1] * rows).floor().long(), 0, rows - 1)
    active = fleet[..., 3]
    occupancy = torch.zeros(n, rows * cols).scatter_add_(1, row * cols + col, active)
    channels = torch.cat([maps, occupancy.view(n, 1, rows, cols)], dim=1)
    padded = torch.nn.functional.pad(channels, (radius,) * 4).permute(0, 2, 3, 1)
    offs = torch.arange(side)
    crop = padded[torch.arange(n).view(n, 1, 1, 1), (row.unsqueeze(-1) + offs).unsqueeze(-1),
                  (col.unsqueeze(-1) + offs).unsqueeze(-2)]  # (N, K, S, S, w+2)
    crop[:, :, radius, radius, -1] -= active
    crop = crop.reshape(n, k, -1)
    return torch.cat([crop, fleet, time.unsqueeze(1).expand(n, k, 2)], dim=-1)


def test_local_observation_equals_the_indexed_crops_exactly():
    gen = torch.Generator().manual_seed(0)
    n, k, rows, cols, radius = 5, 6, 7, 8, 2
    maps = torch.rand((n, 3, rows, cols), generator=gen)
    fleet = torch.rand((n, k, 7), generator=gen)
    fleet[..., 3] = (torch.rand((n, k), generator=gen) > 0.3).float()
    fleet[0, :, :2] = 0.999  # every UAV of day 0 in the north-east corner cell: crops cut by the border, counted
    time = torch.rand((n, 2), generator=gen)
    out = local_observation(maps, fleet, time, radius)
    assert out.shape == (n, k, local_dim(3, radius))
    assert torch.equal(out, indexed_local_observation(maps, fleet, time, radius))


def test_shared_actor_runs_the_layers_of_its_multiagent_mlps():
    """SharedActor's split first layer (channels-last crop part + per-agent embedding part) gives what its torchrl
    MultiAgentMLPs give on the concatenated input with the crop channels first (the weight's order)."""
    torch.manual_seed(0)
    actor = SharedActor(n_agents=4, obs_dim=2 * 9 + 2, embed=3, hidden=8, depth=3, crop=(2, 3))
    local = torch.randn(5, 4, 20)
    channels_first = torch.cat([local[..., :18].unflatten(-1, (3, 3, 2)).permute(0, 1, 4, 2, 3).flatten(2),
                                local[..., 18:]], dim=-1)
    feats = actor.body(torch.cat([channels_first, actor.index.weight.expand(5, -1, -1)], dim=-1))
    pre, got = actor(local)
    torch.testing.assert_close(got, feats)
    torch.testing.assert_close(pre, actor.head(feats))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_untrained_actors_actions_are_near_zero(core, seed):
    """The actor head's last layer starts uniform in +-HEAD_INIT (Lillicrap et al. 2016, section 7): at the paper's
    actor sizes the untrained deterministic actions, on a day of observations, are all within 0.02 of zero (with
    the default init the largest was 0.11-0.20 over seeds 0-4, 0.004 at most with this one)."""
    paper_actor = dataclasses.replace(QUICK, crop_radius=3, index_embed=8, actor_hidden=64, actor_depth=2,
                                      warmup=10 ** 6)
    trainer = Trainer(core=core, settings=paper_actor, seed=seed)
    head = trainer.learner.actor.head.params["0"]
    assert head["weight"].shape == (3, 64) and head["bias"].shape == (3,)
    assert max(head["weight"].abs().max(), head["bias"].abs().max()) <= HEAD_INIT  # the default's bound: 1 / 8
    trainer.run_episode()  # uniform random actions: the fleet and the demand a day visits
    x = trainer.learner.inputs(trainer.replay.take(torch.arange(143)), trainer.maps)
    with torch.no_grad():
        actions = torch.tanh(trainer.learner.actor(x.local)[0])
    assert actions.shape == (143, 3, 3)
    assert actions.abs().max() < 0.02


def test_bfloat16_inputs_are_the_float32_inputs_rounded_once():
    """Learner.inputs in bfloat16 reads the maps rounded once; every observation equals the float32 one rounded."""
    gen = torch.Generator().manual_seed(0)
    days, rows, cols, k, n = 2, 6, 6, 4, 32
    maps = torch.rand((days, 144, rows, cols), generator=gen) * 3
    batch = {"day": torch.randint(0, days, (n,), generator=gen), "slot": torch.randint(0, 143, (n,), generator=gen),
             "fleet": torch.rand((n, k, 7), generator=gen), "time": torch.rand((n, 2), generator=gen),
             "action": torch.rand((n, k, 3), generator=gen), "reward": torch.rand(n, generator=gen),
             "terminated": torch.zeros(n, dtype=torch.bool), "truncated": torch.zeros(n, dtype=torch.bool),
             "next_fleet": torch.rand((n, k, 7), generator=gen), "next_time": torch.rand((n, 2), generator=gen)}
    for name in ("fleet", "next_fleet"):  # the active flag is 0 or 1: the occupancy counts are exact
        batch[name][..., 3] = (batch[name][..., 3] > 0.3).float()
    got = {}
    for dtype in ("float32", "bfloat16"):
        learner = Learner(settings=dataclasses.replace(SMALL, matmul_dtype=dtype), rows=rows, cols=cols, maps=3,
                          n_agents=k)
        got[dtype] = learner.inputs(batch, maps)
    for name in ("local", "joint", "next_local", "next_joint"):
        full, half = getattr(got["float32"], name), getattr(got["bfloat16"], name)
        assert full.dtype == torch.float32 and torch.equal(half, full.to(torch.bfloat16)), name


def test_bfloat16_products_keep_a_gradient_step_close_to_float32():
    """The same learner, batch and random state with float32 and with bfloat16 products: the step's losses and
    mean Q within 2 %, and not identical (the bfloat16 products were used)."""
    maps, rows, cols, k, n = 3, 6, 6, 4, 64
    gen = torch.Generator().manual_seed(0)
    x = Inputs(local=torch.rand((n, k, local_dim(maps, 1)), generator=gen),
               joint=torch.rand((n, maps * rows * cols + 7 * k + 2), generator=gen),
               action=torch.rand((n, k, 3), generator=gen) * 2 - 1, reward=torch.rand(n, generator=gen),
               terminated=torch.zeros(n), next_local=torch.rand((n, k, local_dim(maps, 1)), generator=gen),
               next_joint=torch.rand((n, maps * rows * cols + 7 * k + 2), generator=gen))
    metrics = {}
    for dtype in ("float32", "bfloat16"):
        torch.manual_seed(0)
        learner = Learner(settings=dataclasses.replace(SMALL, matmul_dtype=dtype), rows=rows, cols=cols, maps=maps,
                          n_agents=k)
        metrics[dtype] = [learner.update(x) for _ in range(3)]
    for want, got in zip(metrics["float32"], metrics["bfloat16"], strict=True):
        assert {key: got[key] for key in ("critic", "actor", "q")} == pytest.approx(
            {key: want[key] for key in ("critic", "actor", "q")}, rel=0.02)
    assert metrics["bfloat16"][0]["critic"] != metrics["float32"][0]["critic"]


def test_agent_spread_is_zero_for_identical_agents():
    feats = torch.randn(8, 1, 5).expand(8, 3, 5)
    assert float(agent_spread(feats)) == pytest.approx(0.0, abs=1e-7)
    pair = torch.tensor([[[0.0, 2.0], [2.0, 0.0]]])  # std over the two agents is 1 in each feature
    assert float(agent_spread(pair)) == pytest.approx(1.0)


# ----------------------------------------------------------------------------------- TD target

def test_td_target_bootstraps_on_truncation_and_stops_on_termination(scenario3):
    torch.manual_seed(0)
    learner = Learner(settings=SMALL, rows=6, cols=6, maps=scenario3.obs_window + 1, n_agents=3)
    n, maps = 4, scale_demand(torch.rand(4, 7, 6, 6))
    fleet, time = torch.rand(n, 3, 7), torch.rand(n, 2)
    nxt_maps, nxt_fleet = scale_demand(torch.rand(n, 7, 6, 6)), torch.rand(n, 3, 7)
    x = Inputs(local=learner.local(maps, fleet, time), joint=joint_observation(maps, fleet, time),
               action=torch.rand(n, 3, 3) * 2 - 1, reward=torch.tensor([0.3, -0.2, 0.9, 0.5]),
               terminated=torch.tensor([0.0, 0.0, 0.0, 1.0]),  # rows 0-2 truncated (a day's end), row 3 terminal
               next_local=learner.local(nxt_maps, nxt_fleet, time),
               next_joint=joint_observation(nxt_maps, nxt_fleet, time))
    y = learner.td_target(x)
    with torch.no_grad():
        a_next = torch.tanh(learner.target_actor(x.next_local)[0])
        q_next = learner.target_critic(x.next_joint, a_next)
    assert float(q_next.abs().min()) > 1e-4  # a bootstrap term that shows
    torch.testing.assert_close(y[:3], x.reward[:3] + SMALL.gamma * q_next[:3])
    assert float(y[3]) == pytest.approx(0.5)


def test_replay_marks_the_days_end_as_truncated_not_terminated(core):
    trainer = Trainer(core=core, settings=dataclasses.replace(QUICK, warmup=10 ** 6), seed=0)
    trainer.run_episode()
    data = trainer.replay.data
    assert not bool(data["terminated"][:143].any())
    assert data["truncated"][:143].nonzero().flatten().tolist() == [142]


# ----------------------------------------------------------------------------------- the environment

def test_parallel_env_passes_the_pettingzoo_api_test(core):
    env = parallel_env(core)
    parallel_api_test(env, num_cycles=150)
    assert env.env.core.n_days == core.n_days and env.env.days == [0, 1, 2, 3]
    torch.testing.assert_close(env.env.core.demand, core.demand)


def test_replayed_windows_are_the_observations_the_env_gave(core):
    env = parallel_env(core)
    days = scale_demand(core.demand.reshape(4, 144, 6, 6))
    obs, _ = env.reset(options={"day": 2})
    rng = np.random.default_rng(0)
    for slot in range(143):
        want = window_maps(days, torch.tensor([2]), torch.tensor([slot]), 7)[0]
        torch.testing.assert_close(scale_demand(torch.as_tensor(obs["uav_0"]["demand"])), want)
        obs, *_ = env.step({a: rng.uniform(-1, 1, 3).astype(np.float32) for a in env.agents})


# ----------------------------------------------------------------------------------- training

def test_training_lowers_the_td_loss_on_a_fixed_batch(fitted):
    ctrl, manifest, before, batch = fitted
    with torch.no_grad():
        after = float(ctrl.learner.critic_loss(batch))
    assert manifest["steps"] >= 300
    assert after < 0.5 * before, (before, after)


def test_cross_agent_feature_spread_stays_above_a_floor(fitted):
    ctrl, manifest, _, batch = fitted
    logged = manifest["history"]["diag/agent_feature_std"]
    assert np.isfinite(logged[-1]) and logged[-1] > 0.02
    with torch.no_grad():
        _, feats = ctrl.learner.actor(batch.local)
    assert float(agent_spread(feats)) > 0.02


def test_manifest_records_exactly_the_training_days_used(fitted, core):
    ctrl, manifest, _, _ = fitted
    schedule = day_schedule(core.n_days, 2, 0)
    assert manifest["days"] == [int(DAY_IDS[d]) for d in schedule]
    assert set(manifest["days"]) <= set(DAY_IDS.tolist())
    assert manifest["day_labels"] == [core.day_labels[d] for d in schedule]
    assert manifest["transitions_per_day_episode"] == 143
    assert manifest["n_transitions"] == 143 * len(manifest["days"]) == SMALL.transitions
    assert manifest["read_test_data"] is False
    blob = torch.load(manifest["checkpoint"], weights_only=False)
    replayed = blob["replay"]["data"]["day"]  # the day of every stored transition, episode by episode
    assert [int(DAY_IDS[d]) for d in replayed[::143]] == manifest["days"]
    assert len(replayed) == manifest["n_transitions"]
    history = manifest["history"]
    assert history["step"] == [143, 286] and all(len(v) == 2 for v in history.values())


def test_checkpoint_resumes_to_identical_next_step_losses(core, tmp_path):
    settings = dataclasses.replace(QUICK, transitions=2 * 143, update_every=2)
    a = Trainer(core=core, settings=settings, seed=4)
    a.run_episode()
    a.save(tmp_path / "ckpt.pt", {"run": 1})
    want = a.run_episode()
    b = Trainer(core=core, settings=settings, seed=4)
    torch.manual_seed(123)  # the global RNG moves on: the checkpoint must bring everything back
    b.restore(torch.load(tmp_path / "ckpt.pt", weights_only=False))
    got = b.run_episode()
    assert len(want["updates"]) == 72
    assert got["updates"] == want["updates"]  # every loss of every step, exactly
    assert got["return"] == want["return"]
    for p, q in zip(a.learner.actor.parameters(), b.learner.actor.parameters(), strict=True):
        assert torch.equal(p, q)


def test_fit_continues_a_finished_run_from_its_checkpoint(core, tmp_path):
    first = MADDPGController(name="maddpg", seed=1, options=QUICK).fit(core, run_dir=tmp_path)
    again = MADDPGController(name="maddpg", seed=1, options=QUICK)
    second = again.fit(core, run_dir=tmp_path)
    assert second["days"] == first["days"] and second["steps"] == first["steps"] == 44
    assert second["history"] == first["history"]


# ----------------------------------------------------------------------------------- acting

def make(seed, options):
    return MADDPGController(name="maddpg", seed=seed, options=options)


def test_actions_are_bounded_and_moves_stay_within_dmax(fitted, core):
    moved = check_actions_bounded_and_moves_within_dmax(fitted[0], core)
    assert moved > 0.1 * core.scenario.d_max_m  # the policy does move the fleet


def test_same_seed_same_actions(core, tmp_path):
    check_same_seed_same_actions(make, QUICK, core, tmp_path)


def test_save_load_round_trip_and_checks(fitted, core, tmp_path):
    check_save_load(fitted[0], make, SMALL, dataclasses.replace(SMALL, actor_hidden=8), core, tmp_path)


def test_trains_on_the_training_days_of_a_tensor_and_evaluates_batched_as_alone(scenario3, tmp_path):
    options = dataclasses.replace(QUICK, transitions=3 * 143, warmup=400)
    check_trains_on_training_days_and_evaluates_batched_as_alone(make, options, scenario3, tmp_path)
