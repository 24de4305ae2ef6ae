"""MADDPG: local observations, the centralized critic's actor objective, the TD target at a day's end, training
on small synthetic days (loss, cross-agent spread, checkpoint resumption, recorded days, seeds), acting within
bounds, and the PettingZoo parallel environment it trains through."""
import dataclasses

import numpy as np
import pytest
import torch
from pettingzoo.test import parallel_api_test

from dswm.config import ConfigError
from dswm.methods.base import DayContext
from dswm.methods.maddpg import MADDPGController, MADDPGSettings
from dswm.methods.maddpg.learner import Inputs, Learner
from dswm.methods.maddpg.networks import (CentralCritic, agent_spread, joint_observation, local_dim,
                                          local_observation, scale_demand)
from dswm.methods.maddpg.replay import window_maps
from dswm.methods.maddpg.training import Trainer, day_schedule, parallel_env
from dswm.sim.core import FleetCore, Grid, initial_positions
from dswm.sim.env import synthetic_demand
from dswm.sim.fleet import ACTIVE
from dswm.pipeline.jobs import training_core
from dswm.protocol.evaluation import evaluate
from prep.tensor import DemandTensor, GridSpec

GRID = Grid(rows=6, cols=6, cell_m=235.0)
DAY_IDS = np.array([2, 5, 7, 11])  # tensor days of the core's four training days
SMALL = MADDPGSettings(crop_radius=1, index_embed=4, actor_hidden=16, actor_depth=2, critic_hidden=32, critic_depth=2,
                       actor_lr=1e-3, critic_lr=1e-3, gamma=0.5, tau=0.05, noise_std=0.2, action_reg=1e-3,
                       grad_clip=1.0, buffer_size=1000, batch_size=32, warmup=100, transitions=2 * 143,
                       update_every=1, gradient_steps=2, log_points=10, checkpoint_every=1)
QUICK = dataclasses.replace(SMALL, transitions=143, gradient_steps=1)  # one day-episode, 44 gradient steps


@pytest.fixture(scope="module")
def scenario3(scenario):
    return dataclasses.replace(scenario, n_uavs=3)


@pytest.fixture(scope="module")
def core(scenario3):
    demand = synthetic_demand(days=4, rows=GRID.rows, cols=GRID.cols, slots=scenario3.slots_per_day, seed=3)
    c = FleetCore(demand=demand, grid=GRID, scenario=scenario3,
                  init_pos=initial_positions(demand.mean(axis=(0, 1)), GRID, scenario3.n_uavs, 0),
                  dataset="toy", day_labels=[f"2024-01-{d:02d}" for d in DAY_IDS])
    c.day_ids = DAY_IDS
    return c


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


def contexts(core, days):
    return [DayContext(dataset="toy", day=int(d), label=core.day_labels[d], split="train", grid=core.grid,
                       scenario=core.scenario, geometry=core.geom, cells=core.cells,
                       init_pos=core.init_pos.numpy()) for d in days]


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
    crop = out[0, :, :27].reshape(3, 3, 3, 3)  # (agent, channel, row, col)
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

def test_actions_are_bounded_and_moves_stay_within_dmax(fitted, core):
    ctrl = fitted[0]
    ctrl.reset_batch(contexts(core, [0, 3]))
    obs = core.reset([0, 3])
    d_max, moved = core.scenario.d_max_m, 0.0
    for _ in range(143):
        action = ctrl.act_batch(obs)
        assert action.shape == (2, 3, 3) and action.dtype == np.float32
        assert np.all(np.abs(action) <= 1.0)
        pos, active = core.state.pos.clone(), core.state.status == ACTIVE
        obs = core.step(action).obs
        step = torch.linalg.norm(core.state.pos - pos, dim=-1)[active]
        if len(step):
            assert float(step.max()) <= d_max * (1 + 1e-5)
            moved = max(moved, float(step.max()))
    assert moved > 0.1 * d_max  # the policy does move the fleet


def test_same_seed_same_actions(core, tmp_path):
    obs = core.reset([1, 2])
    acts = []
    for seed, run in ((0, "a"), (0, "b"), (1, "c")):
        ctrl = MADDPGController(name="maddpg", seed=seed, options=QUICK)
        ctrl.fit(core, run_dir=tmp_path / run)
        ctrl.reset_batch(contexts(core, [1, 2]))
        acts.append(ctrl.act_batch(obs))
    assert np.array_equal(acts[0], acts[1])
    assert not np.allclose(acts[0], acts[2])
    single = ctrl.act({k: v[1] for k, v in obs.items()})
    np.testing.assert_allclose(single, acts[2][1], rtol=1e-5, atol=1e-6)


def test_save_load_round_trip_and_checks(fitted, core, tmp_path):
    ctrl = fitted[0]
    ctrl.save(tmp_path / "model.pt")
    loaded = MADDPGController(name="maddpg", seed=0, options=SMALL)
    loaded.load(tmp_path / "model.pt")
    loaded.reset_batch(contexts(core, [0]))
    obs = core.reset([0])
    np.testing.assert_array_equal(loaded.act_batch(obs), ctrl.act_batch(obs))
    wider = MADDPGController(name="maddpg", seed=0, options=dataclasses.replace(SMALL, actor_hidden=8))
    with pytest.raises(ValueError, match="architecture"):
        wider.load(tmp_path / "model.pt")
    other = dataclasses.replace(contexts(core, [0])[0], grid=Grid(rows=7, cols=6, cell_m=235.0))
    with pytest.raises(ValueError, match="6x6 grid"):
        loaded.reset_batch([other])


def test_trains_on_the_training_days_of_a_tensor_and_evaluates_batched_as_alone(scenario3, tmp_path):
    """The train rule's core holds the tensor's training days only; evaluation batched or day by day agrees."""
    demand = np.concatenate([synthetic_demand(days=5, rows=6, cols=6, seed=9)[:3] * 0.5,
                             synthetic_demand(days=2, rows=6, cols=6, seed=10) * 2.0])  # test days look different
    days = [{"index": i, "label": f"d{i}", "split": "train" if i in (0, 2, 4) else "test", "weekday": i % 7,
             "weekend": False} for i in range(5)]
    demand = demand[[0, 3, 1, 4, 2]]  # training days 0, 2, 4 (from the first draw), test days 1, 3
    meta = {"dataset": "toy", "source": "demo", "days": days, "slots_per_day": 144,
            "eval_days": {"id": [1], "ood": [3]}, "grid": {"rows": 6, "cols": 6, "cell_m": 235.0}}
    tensor = DemandTensor(demand=demand, meta=meta, grid=GridSpec(rows=6, cols=6, cell_m=235.0))
    train = training_core(tensor, scenario3)
    assert train.n_days == 3
    torch.testing.assert_close(train.demand, torch.as_tensor(demand[[0, 2, 4]]).reshape(3, 144, 36))
    ctrl = MADDPGController(name="maddpg", seed=0, options=dataclasses.replace(QUICK, transitions=3 * 143, warmup=400))
    manifest = ctrl.fit(train, run_dir=tmp_path)
    assert sorted(manifest["days"]) == [0, 2, 4] and manifest["day_labels"] == [f"d{d}" for d in manifest["days"]]
    runs = [evaluate(tensor=tensor, controller=ctrl, scenario=scenario3, seed=0, limits={"id": None, "ood": None},
                     profile="smoke", device="cpu", batch_days=b, progress_interval_s=5.0).days for b in (True, False)]
    assert runs[0]["day"].to_list() == [1, 3]
    cols = ["sr_mean", "energy_kj_per_slot", "jain"]
    np.testing.assert_allclose(runs[0].select(cols).to_numpy(), runs[1].select(cols).to_numpy(), rtol=1e-5)
