"""Model-free RL with SB3 (ppo, sac): the API checkers of the Gymnasium and PettingZoo views, the flat
observation, FleetVecEnv's VecEnv contract, learning (losses on fixed batches), checkpoints that resume exactly,
TD targets that bootstrap at the day's truncation, actions, the manifest's days and seeds."""
import copy
import dataclasses
import functools
import warnings

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from pettingzoo.test import parallel_api_test
from stable_baselines3 import PPO
from stable_baselines3 import SAC as SB3SAC
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_checker import check_env
from stable_baselines3.common.logger import configure

from dswm.config import ConfigError
from dswm.methods.base import DayContext
from dswm.methods.rl.spaces import (FlatFleetEnv, flat_action, flat_observation, fleet_action, observation_dim,
                                    observation_space)
from dswm.methods.rl.vec_env import FleetVecEnv
from dswm.methods.matmul import MatmulLinear, forget_casts, keep_casts, linear, set_matmul_dtype
from dswm.methods.rl.sac_train import SAC, ReplayBuffer
from dswm.methods.rl.sb3 import CHECKPOINT, PPOController, SACController
from dswm.sim.core import FleetCore, Grid, fleet_state_from_obs, initial_positions
from dswm.sim.env import UAVFleetEnv, UAVFleetParallelEnv, synthetic_demand
from dswm.sim.fleet import ACTIVE

GRID = Grid(rows=6, cols=6, cell_m=235.0)
K = 3
DAY_IDS = np.array([2, 5, 7, 9])  # tensor days of the core's 4 training days
LABELS = ["d2", "d5", "d7", "d9"]
HORIZON = 143
D = 7 * 36 + 7 * K + 2

PPO_OPTIONS = {"n_envs": 2, "day_episodes": 4, "net_arch": [32, 32], "learning_rate": 1.0e-3, "gamma": 0.9,
               "batch_size": 143, "checkpoint_every": 1, "n_epochs": 4, "gae_lambda": 0.95, "clip_range": 0.2,
               "ent_coef": 0.0, "vf_coef": 0.5, "max_grad_norm": 0.5, "log_std_init": -0.5, "use_sde": False,
               "sde_sample_freq": 4}
SAC_OPTIONS = {"n_envs": 2, "day_episodes": 4, "net_arch": [32, 32], "learning_rate": 1.0e-3, "gamma": 0.9,
               "batch_size": 64, "checkpoint_every": 1, "buffer_size": 3000, "learning_starts": 100, "tau": 0.05,
               "train_freq": 1, "gradient_steps": 1, "ent_coef_init": 0.1, "auto_entropy": True,
               "matmul_dtype": "float32"}
METHODS = {"ppo": (PPOController, PPO_OPTIONS), "sac": (SACController, SAC_OPTIONS)}


@pytest.fixture(scope="module")
def small(scenario):
    return dataclasses.replace(scenario, n_uavs=K)


def make_core(small) -> FleetCore:
    demand = synthetic_demand(days=4, rows=6, cols=6, slots=small.slots_per_day, seed=3)
    core = FleetCore(demand=demand, grid=GRID, scenario=small, dataset="toy", day_labels=LABELS,
                     init_pos=initial_positions(demand.mean(axis=(0, 1)), GRID, K, 0))
    core.day_ids = DAY_IDS
    return core


def controller(method, seed=0, **changes):
    cls, options = METHODS[method]
    opts = cls.options_from_plain(name=method, data={**options, **changes})
    return cls(name=method, seed=seed, device="cpu", options=opts)


def fit(method, small, run_dir, seed=0, **changes):
    torch.set_num_threads(1)
    ctl = controller(method, seed, **changes)
    return ctl, ctl.fit(make_core(small), run_dir=run_dir)


@pytest.fixture(scope="module")
def fitted(small, tmp_path_factory):
    """Each method fitted once: 4 day-episodes in 2 rounds of 2 days, a checkpoint after each round."""
    out = {}
    for method in METHODS:
        run_dir = tmp_path_factory.mktemp(method)
        out[method] = (*fit(method, small, run_dir), run_dir)
    return out


def contexts(small, days):
    core = make_core(small)
    return [DayContext(dataset="toy", day=int(d), label=LABELS[d], split="id", grid=GRID, scenario=small,
                       geometry=GRID.geometry(), cells=GRID.cells(), init_pos=core.init_pos.numpy()) for d in days]


def run_actions(ctl, small, days, slots):
    """Actions of ``ctl`` over ``slots`` slots of ``days``, and the largest move of an active UAV."""
    core = make_core(small)
    obs = core.reset(days)
    ctl.reset_batch(contexts(small, days))
    actions, largest = [], 0.0
    for _ in range(slots):
        a = ctl.act_batch(obs)
        before = fleet_state_from_obs(obs["fleet"], GRID, small)
        obs = core.step(a).obs
        after = fleet_state_from_obs(obs["fleet"], GRID, small)
        moved = torch.linalg.vector_norm(after.pos - before.pos, dim=-1)[before.status == ACTIVE]
        largest = max(largest, float(moved.max()))
        actions.append(a)
    return np.stack(actions), largest


# ----------------------------------------------------------------------------------- checkers and spaces

def test_sb3_check_env_and_pettingzoo_parallel_api_pass_on_the_views(small):
    demand = synthetic_demand(days=3, rows=6, cols=6, slots=small.slots_per_day)
    check_env(UAVFleetEnv(demand=demand, grid=GRID, scenario=small), warn=False)  # the dict view
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the flat view draws no warning from SB3's checker
        check_env(FlatFleetEnv(UAVFleetEnv(demand=demand, grid=GRID, scenario=small)), warn=True)
    parallel_api_test(UAVFleetParallelEnv(demand=demand, grid=GRID, scenario=small), num_cycles=150)


def test_flat_observation_is_log1p_demand_then_fleet_then_time(small):
    core = make_core(small)
    core.reset([1, 3])
    for _ in range(8):
        out = core.step(np.full((2, K, 3), 0.5, dtype=np.float32))
    obs = out.obs
    flat = flat_observation(obs)
    assert observation_dim(6, 6, small) == D and flat.shape == (2, D) and flat.dtype == np.float32
    np.testing.assert_allclose(flat[:, :252], np.log1p(obs["demand"].reshape(2, -1)), rtol=1e-6)
    assert np.array_equal(flat[:, 252:252 + 7 * K], obs["fleet"].reshape(2, -1))
    assert np.array_equal(flat[:, -2:], obs["time"])
    assert flat[0, -2:] == pytest.approx([np.sin(2 * np.pi * 8 / 144), np.cos(2 * np.pi * 8 / 144)], abs=1e-6)
    assert observation_space(6, 6, small).contains(flat[0])
    a = np.random.default_rng(0).uniform(-1, 1, (2, K, 3)).astype(np.float32)
    assert flat_action(a).shape == (2, 3 * K) and np.array_equal(fleet_action(flat_action(a), K), a)
    assert np.array_equal(flat_action(a)[1, 3:6], a[1, 1])
    with pytest.raises(ValueError, match=r"expected shape \(B, 9\)"):
        fleet_action(np.zeros((2, 8)), K)


# ----------------------------------------------------------------------------------- FleetVecEnv

def test_fleet_vec_env_steps_the_core_and_truncates_every_day_together(small):
    env = FleetVecEnv(make_core(small), n_envs=3, seed=11)
    draws = np.random.default_rng(11)
    first, second = draws.integers(4, size=3), draws.integers(4, size=3)
    ref = make_core(small)
    obs = env.reset()
    assert obs.shape == (3, D) and obs.dtype == np.float32
    assert env.observation_space.shape == (D,) and env.action_space.shape == (3 * K,)
    assert env.action_space.low.min() == -1 and env.action_space.high.max() == 1
    assert np.array_equal(obs, flat_observation(ref.reset(first)))
    rng = np.random.default_rng(0)
    total = np.zeros(3)
    for t in range(HORIZON):
        a = rng.uniform(-1, 1, (3, 3 * K)).astype(np.float32)
        obs, reward, done, infos = env.step(a)
        expected = ref.step(fleet_action(a, K))
        total += expected.reward
        assert reward.dtype == np.float32 and reward.shape == (3,) and done.shape == (3,)
        assert np.array_equal(reward, expected.reward.astype(np.float32))
        if t < HORIZON - 1:
            assert not done.any() and all("terminal_observation" not in i for i in infos)
            assert np.array_equal(obs, flat_observation(expected.obs))
    assert done.all()
    terminal = flat_observation(expected.obs)
    for i, info in enumerate(infos):
        assert info["TimeLimit.truncated"] is True
        assert np.array_equal(info["terminal_observation"], terminal[i])
        assert info["terminal_observation"][-2:] == pytest.approx([np.sin(2 * np.pi * 143 / 144),
                                                                   np.cos(2 * np.pi * 143 / 144)], abs=1e-6)
        assert info["day"] == DAY_IDS[first[i]]
        assert info["episode"]["r"] == pytest.approx(total[i], rel=1e-5) and info["episode"]["l"] == HORIZON
    # auto-reset: the returned observation starts the next round's days at slot 0
    assert np.array_equal(obs, flat_observation(make_core(small).reset(second)))
    assert env.episodes == first.tolist() and env.episode_days() == DAY_IDS[first].tolist()
    assert env.transitions == 3 * HORIZON
    assert env.get_attr("n_uavs") == [K] * 3 and env.env_is_wrapped(object) == [False] * 3
    assert env.env_method("episode_days", indices=[0, 2]) == [DAY_IDS[first].tolist()] * 2


# ----------------------------------------------------------------------------------- learning

def test_ppo_lowers_its_value_loss_on_a_fixed_batch(small, fitted):
    ctl, _, _ = fitted["ppo"]
    core, gamma = make_core(small), PPO_OPTIONS["gamma"]
    obs, rng, states, rewards = core.reset([0, 3]), np.random.default_rng(5), [], []
    for _ in range(HORIZON):
        states.append(flat_observation(obs))
        out = core.step(rng.uniform(-1, 1, (2, K, 3)).astype(np.float32))
        rewards.append(out.reward)
        obs = out.obs
    returns, acc = np.zeros((HORIZON, 2)), np.zeros(2)
    for t in reversed(range(HORIZON)):
        acc = rewards[t] + gamma * acc
        returns[t] = acc
    x = torch.as_tensor(np.stack(states)[:100].reshape(-1, D))  # far from the day's end: gamma^43 ~ 0.01
    target = returns[:100].reshape(-1)

    def value_loss(model):
        with torch.no_grad():
            return float(np.mean((model.policy.predict_values(x).numpy().reshape(-1) - target) ** 2))

    untrained = ctl.build_algorithm(FleetVecEnv(make_core(small), n_envs=2, seed=0))  # same seed: same init
    before, after = value_loss(untrained), value_loss(ctl.model)
    assert before > 10.0
    assert after < 0.4 * before


def sac_critic_loss(model, buffer, n):
    """SAC's critic loss (SB3's formula) on the first n stored transitions of env 0."""
    torch.manual_seed(0)
    obs, nxt = torch.as_tensor(buffer.observations[:n, 0]), torch.as_tensor(buffer.next_observations[:n, 0])
    act = torch.as_tensor(buffer.actions[:n, 0])
    reward = torch.as_tensor(buffer.rewards[:n, 0]).reshape(-1, 1)
    done = torch.as_tensor(buffer.dones[:n, 0] * (1 - buffer.timeouts[:n, 0])).reshape(-1, 1)
    with torch.no_grad():
        next_act, logp = model.actor.action_log_prob(nxt)
        next_q = torch.min(torch.cat(model.critic_target(nxt, next_act), dim=1), dim=1, keepdim=True).values
        alpha = torch.exp(model.log_ent_coef)
        y = reward + (1 - done) * model.gamma * (next_q - alpha * logp.reshape(-1, 1))
        return float(0.5 * sum(F.mse_loss(q, y) for q in model.critic(obs, act)))


def test_sac_lowers_its_critic_loss_on_a_fixed_batch(small, fitted):
    ctl, _, _ = fitted["sac"]
    buffer = ctl.model.replay_buffer
    untrained = ctl.build_algorithm(FleetVecEnv(make_core(small), n_envs=2, seed=0))
    before, after = sac_critic_loss(untrained, buffer, 280), sac_critic_loss(ctl.model, buffer, 280)
    assert after < 0.7 * before


# ----------------------------------------------------------------------------------- truncation

def test_sac_stores_the_days_end_as_a_timeout_with_its_terminal_observation(fitted):
    buffer = fitted["sac"][0].model.replay_buffer
    n = buffer.pos
    assert n == 4 * HORIZON // 2 and not buffer.full
    slot = np.rint(np.arctan2(buffer.observations[:n, :, -2], buffer.observations[:n, :, -1])
                   * 144 / (2 * np.pi)) % 144
    next_slot = np.rint(np.arctan2(buffer.next_observations[:n, :, -2], buffer.next_observations[:n, :, -1])
                        * 144 / (2 * np.pi)) % 144
    end = slot == HORIZON - 1
    assert end.sum() == 4  # one day's end per episode
    assert np.array_equal(next_slot[end], np.full(4, 143.0))  # the terminal observation, not the next day's o_0
    assert np.array_equal(next_slot[~end], slot[~end] + 1)
    assert buffer.dones[:n][end].tolist() == [1.0] * 4 and buffer.timeouts[:n][end].tolist() == [1.0] * 4
    assert not buffer.dones[:n][~end].any()
    assert not (buffer.dones[:n] * (1 - buffer.timeouts[:n])).any()  # the done SB3's TD target uses: none
    assert float(buffer.sample(512).dones.sum()) == 0.0


class _LastStep(BaseCallback):
    """Keeps the raw rewards and the value of the terminal observations at the rollout's day end."""

    def _on_step(self) -> bool:
        if self.locals["dones"].all():
            self.raw = self.locals["rewards"].copy()
            term = np.stack([i["terminal_observation"] for i in self.locals["infos"]])
            assert all(i["TimeLimit.truncated"] for i in self.locals["infos"])
            with torch.no_grad():
                self.value = self.model.policy.predict_values(torch.as_tensor(term)).numpy().reshape(-1)
        return True


def test_ppo_adds_gamma_times_the_terminal_value_to_a_truncated_days_last_reward(small):
    ctl = controller("ppo")
    model = ctl.build_algorithm(FleetVecEnv(make_core(small), n_envs=2, seed=0))
    cb = _LastStep()
    model.learn(total_timesteps=2 * HORIZON, callback=cb)
    stored = model.rollout_buffer.rewards[-1]
    assert np.abs(cb.value).min() > 1e-3  # a bootstrap that shows
    np.testing.assert_allclose(stored, cb.raw + PPO_OPTIONS["gamma"] * cb.value, rtol=0, atol=1e-6)
    assert not model.rollout_buffer.episode_starts[-1].any()


# ----------------------------------------------------------------------------------- checkpoints and files

@pytest.mark.parametrize("method", ["ppo", "sac"])
def test_checkpoint_resumes_to_the_uninterrupted_run(method, small, fitted, tmp_path, monkeypatch):
    ctl_a, man_a, _ = fitted[method]
    _, man_b = fit(method, small, tmp_path, day_episodes=2)  # stopped after the first round
    assert (tmp_path / CHECKPOINT).is_file()
    calls = []
    algorithm = METHODS[method][0].algorithm
    learn = algorithm.learn
    monkeypatch.setattr(algorithm, "learn", lambda self, *a, **k: calls.append(1) or learn(self, *a, **k))
    ctl_c, man_c = fit(method, small, tmp_path)  # a new process would do the same: everything comes from the file
    assert len(calls) == 1  # only the second round was trained
    assert man_c["days"] == man_a["days"] and man_c["steps"] == man_a["steps"]
    assert man_c["history"].keys() == man_a["history"].keys()
    for name, values in man_a["history"].items():
        np.testing.assert_array_equal(man_c["history"][name], values, err_msg=name)  # the next update's losses
    assert man_b["history"]["step"] == [2 * HORIZON]
    params_a, params_c = ctl_a.model.get_parameters(), ctl_c.model.get_parameters()
    for part in params_a:
        for key, value in params_a[part].items():
            if isinstance(value, torch.Tensor):
                assert torch.equal(params_c[part][key], value), (part, key)


@pytest.mark.parametrize("method", ["ppo", "sac"])
def test_model_file_round_trips_under_its_own_name(method, small, fitted, tmp_path):
    ctl, _, _ = fitted[method]
    path = tmp_path / "model.pt"
    ctl.save(path)
    assert path.is_file() and not (tmp_path / "model.pt.zip").exists()
    state = np.random.get_state()[1].copy()
    other = controller(method, seed=5)
    other.load(path)
    assert np.array_equal(np.random.get_state()[1], state)  # loading leaves the process's RNGs alone
    a, _ = run_actions(ctl, small, [0, 2], 5)
    b, _ = run_actions(other, small, [0, 2], 5)
    assert np.array_equal(a, b)
    wrong = controller("sac" if method == "ppo" else "ppo")
    with pytest.raises(ValueError, match="model, expected"):
        wrong.load(path)


# ----------------------------------------------------------------------------------- acting, manifest, seeds

@pytest.mark.parametrize("method", ["ppo", "sac"])
def test_actions_are_in_range_and_no_uav_moves_more_than_d_max(method, small, fitted):
    actions, largest = run_actions(fitted[method][0], small, [0, 1, 2, 3], 20)
    assert actions.shape == (20, 4, K, 3) and actions.dtype == np.float32
    assert actions.min() >= -1.0 and actions.max() <= 1.0
    assert np.abs(actions).max() > 0.05  # the policy acts
    assert largest <= small.d_max_m + 1e-3
    with pytest.raises(ValueError, match="grid"):
        fitted[method][0].reset_batch([dataclasses.replace(contexts(small, [0])[0], grid=Grid(rows=5, cols=6,
                                                                                             cell_m=235.0))])


@pytest.mark.parametrize("method", ["ppo", "sac"])
def test_the_evaluation_acts_with_the_policys_mean_and_sampling_is_the_diagnostics_choice(method, small, fitted):
    """act_batch is the policy's mean (what every evaluation scores); with ``deterministic`` False it samples the
    policy as training does: around that mean, by the policy's std (SAC squashes its sample, PPO clips it)."""
    ctl = fitted[method][0]
    mean, _ = run_actions(ctl, small, [0, 1], 1)
    again, _ = run_actions(ctl, small, [0, 1], 1)
    assert np.array_equal(mean, again)
    ctl.deterministic = False
    try:
        draws = np.stack([run_actions(ctl, small, [0, 1], 1)[0] for _ in range(20)])
    finally:
        ctl.deterministic = True
    spread = draws.std(0)
    assert spread.min() > 0.01  # every coordinate varies between draws
    assert np.abs(draws.mean(0) - mean).mean() < spread.mean()  # centred near the mean action
    assert np.array_equal(run_actions(ctl, small, [0, 1], 1)[0], mean)


def test_ppo_with_gsde_samples_a_state_dependent_noise_held_until_its_matrix_is_drawn_again(small, tmp_path):
    """``use_sde``: SB3's gSDE, trained with the matrix drawn every ``sde_sample_freq`` slots. Its noise is a linear map
    of the last hidden features: the same state under the same matrix gets the same sample, a new matrix another."""
    ctl, _ = fit("ppo", small, tmp_path, use_sde=True, sde_sample_freq=4)
    policy = ctl.model.policy
    assert policy.use_sde and ctl.model.sde_sample_freq == 4
    assert tuple(policy.log_std.shape) == (32, 3 * K)  # one scale per (hidden feature, action), not per action
    mean, _ = run_actions(ctl, small, [0, 1], 1)
    ctl.deterministic = False
    try:
        first, _ = run_actions(ctl, small, [0, 1], 1)
        again, _ = run_actions(ctl, small, [0, 1], 1)
        policy.reset_noise(2)
        redrawn, _ = run_actions(ctl, small, [0, 1], 1)
    finally:
        ctl.deterministic = True
    assert np.array_equal(first, again)
    assert np.abs(first - mean).mean() > 0.01 and np.abs(redrawn - first).mean() > 0.01
    assert np.array_equal(run_actions(ctl, small, [0, 1], 1)[0], mean)


@pytest.mark.parametrize("method", ["ppo", "sac"])
def test_manifest_lists_exactly_the_training_days_of_the_episodes_used(method, fitted):
    _, man, run_dir = fitted[method]
    draws = np.random.default_rng(0)
    rows = np.concatenate([draws.integers(4, size=2) for _ in range(2)])
    assert man["days"] == DAY_IDS[rows].tolist() and set(man["days"]) <= set(DAY_IDS.tolist())
    assert man["day_labels"] == [LABELS[r] for r in rows]
    assert man["n_transitions"] == HORIZON * len(man["days"]) == 4 * HORIZON
    assert man["transitions_per_day_episode"] == HORIZON and man["read_test_data"] is False
    assert man["checkpoint"] == str(run_dir / CHECKPOINT)
    expected_steps = 2 * 4 * 2 if method == "ppo" else HORIZON * 2 - 50  # PPO: rollouts x epochs x minibatches
    assert man["steps"] == expected_steps  # SAC: one per vectorized step after 100 transitions
    history = man["history"]
    assert history["step"] == [2 * HORIZON, 4 * HORIZON]
    assert all(len(v) == 2 for v in history.values())
    loss = "train/value_loss" if method == "ppo" else "train/critic_loss"
    assert np.isfinite(history[loss]).all() and np.isfinite(history["rollout/ep_rew_mean"]).all()


@pytest.mark.parametrize("method", ["ppo", "sac"])
def test_same_seed_same_actions_after_fit(method, small, fitted, tmp_path):
    again, _ = fit(method, small, tmp_path / "again")
    other, _ = fit(method, small, tmp_path / "other", seed=1)
    a, _ = run_actions(fitted[method][0], small, [1, 3], 6)
    b, _ = run_actions(again, small, [1, 3], 6)
    c, _ = run_actions(other, small, [1, 3], 6)
    assert np.array_equal(a, b)
    assert np.abs(a - c).max() > 1e-3


def test_settings_name_the_bad_key(small, tmp_path):
    with pytest.raises(ConfigError, match=r"methods\.ppo\.day_episodes.*multiple of n_envs"):
        controller("ppo", day_episodes=3)
    with pytest.raises(ConfigError, match=r"methods\.sac\.net_arch"):
        controller("sac", net_arch=[])
    with pytest.raises(ConfigError, match=r"methods\.ppo\.batch_size.*286"):
        controller("ppo", batch_size=100).fit(make_core(small), run_dir=tmp_path)


# ----------------------------------------------------------------------------------- the leaner SAC step

def build_sac(scenario, cls, **extra):
    """``cls`` (SB3's SAC or dswm's) with SACController's arguments on 2 training days of ``scenario``, no gradient
    step before 10^6 transitions, SB3's float32 products and replay buffer unless ``extra`` says otherwise."""
    kwargs = {**controller("sac").algorithm_kwargs(HORIZON), "learning_starts": 10 ** 6,
              "replay_buffer_kwargs": {"handle_timeout_termination": True}}
    kwargs.pop("matmul_dtype"), kwargs.pop("replay_buffer_class")
    return cls("MlpPolicy", FleetVecEnv(make_core(scenario), n_envs=2, seed=0), seed=0, device="cpu", verbose=0,
               **{**kwargs, **extra})


def sac_losses_after_steps(model, n: int) -> tuple[dict[str, float], dict[str, torch.Tensor]]:
    """The logged mean losses of ``n`` gradient steps from fixed random draws, and the policy's weights after."""
    model.set_logger(configure(None, []))
    np.random.seed(1)
    torch.manual_seed(1)
    model.train(gradient_steps=n, batch_size=64)
    losses = {k: float(model.logger.name_to_value[f"train/{k}"]) for k in ("critic_loss", "actor_loss", "ent_coef")}
    return losses, {k: v.detach().clone() for k, v in model.policy.state_dict().items()}


def test_sac_gradient_step_is_sb3s_in_float32_and_stays_close_in_bfloat16(small):
    """dswm's SAC (dswm.methods.rl.sac_train) against stable_baselines3.SAC's own train() from the same weights,
    replay buffer and random draws: in float32 the same losses and weights up to float rounding (bit for bit on
    one CPU; on another, with AMX, the weights differ by up to ~4e-9 after 3 steps, a difference in the last bits
    of float kernels whose place was not isolated); with bfloat16 products the losses within 2 %."""
    torch.set_num_threads(1)
    build = functools.partial(build_sac, small)
    reference = build(SB3SAC)
    reference.learn(total_timesteps=2 * HORIZON)  # fills the buffer with random actions, no gradient step
    reference_start = {k: v.detach().clone() for k, v in reference.policy.state_dict().items()}
    assert reference._n_updates == 0 and reference.replay_buffer.size() == HORIZON
    runs = {}
    for dtype in ("float32", "bfloat16"):
        fast = build(SAC, matmul_dtype=dtype)
        fast.policy.load_state_dict(reference.policy.state_dict())
        fast.replay_buffer = copy.deepcopy(reference.replay_buffer)
        runs[dtype] = sac_losses_after_steps(fast, 3)
    want, want_weights = sac_losses_after_steps(reference, 3)
    got, got_weights = runs["float32"]
    assert got == pytest.approx(want, rel=1e-6)
    assert want_weights.keys() == got_weights.keys()
    for name, value in want_weights.items():
        torch.testing.assert_close(got_weights[name], value, rtol=1e-6, atol=1e-7, msg=name)
    assert any(not torch.equal(want_weights[name], value) for name, value in reference_start.items())  # trained
    half, _ = runs["bfloat16"]
    assert half == pytest.approx(want, rel=0.02)
    assert half["critic_loss"] != want["critic_loss"]  # the bfloat16 products were used


def test_sac_bfloat16_step_with_its_bfloat16_buffer_is_sb3s_step_with_bfloat16_layers(small):
    """With bfloat16 products dswm's SAC stores the observations rounded to bfloat16, rounds each weight once per
    change and computes no gradient for the critics' observation columns; it computes what SB3's own train()
    computes with every Linear layer's product in bfloat16 (``set_matmul_dtype`` on its policy), from the same
    weights, transitions and random draws: the same losses and weights (bit for bit here; the float32 test's
    tolerance, for the last bits of float kernels on other CPUs)."""
    torch.set_num_threads(1)
    build = functools.partial(build_sac, small)
    reference = build(SB3SAC)
    reference.learn(total_timesteps=2 * HORIZON)
    set_matmul_dtype(reference.policy, "bfloat16")
    fast = build(SAC, matmul_dtype="bfloat16", replay_buffer_class=ReplayBuffer,
                 replay_buffer_kwargs={"handle_timeout_termination": True, "observation_dtype": "bfloat16"})
    fast.policy.load_state_dict(reference.policy.state_dict())
    src, dst = reference.replay_buffer, fast.replay_buffer
    assert dst.observations.dtype == np.uint16 and dst.observations.nbytes * 2 == src.observations.nbytes
    for i in range(src.pos):  # the same transitions, through the buffer's own add
        dst.add(src.observations[i], src.next_observations[i], src.actions[i], src.rewards[i], src.dones[i],
                [{"TimeLimit.truncated": bool(t)} for t in src.timeouts[i]])
    np.testing.assert_array_equal(dst.timeouts[:dst.pos], src.timeouts[:src.pos])
    sample = dst.sample(5)
    assert sample.observations.dtype == sample.next_observations.dtype == torch.bfloat16
    stored = torch.from_numpy(dst.observations[:dst.pos]).view(torch.bfloat16)
    torch.testing.assert_close(stored, torch.from_numpy(src.observations[:src.pos]).bfloat16(), rtol=0, atol=0)
    want, want_weights = sac_losses_after_steps(reference, 3)
    got, got_weights = sac_losses_after_steps(fast, 3)
    assert got == pytest.approx(want, rel=1e-6)
    for name, value in want_weights.items():
        torch.testing.assert_close(got_weights[name], value, rtol=1e-6, atol=1e-7, msg=name)
    assert all(sub._low_weight is None and not sub.keep_cast for sub in fast.policy.modules()
               if isinstance(sub, MatmulLinear))  # no rounded copy outlives the step


def test_matmul_linear_keeps_its_rounded_weight_until_told_and_its_gradients_are_linears():
    """A MatmulLinear keeping its cast reuses the rounded weight after the weight changes (the owner must call
    forget_casts), and its product and gradients (forward and forward_tail) equal matmul.linear's."""
    torch.manual_seed(0)
    layer = set_matmul_dtype(torch.nn.Sequential(torch.nn.Linear(7, 5)), "bfloat16")[0]
    x_fixed, tail = torch.randn(4, 4), torch.randn(4, 3, requires_grad=True)
    x = torch.cat([x_fixed, tail], dim=1)
    want = linear(x, layer.weight, layer.bias, torch.bfloat16)
    want.square().sum().backward()
    want_grads = (tail.grad.clone(), layer.weight.grad.clone(), layer.bias.grad.clone())
    tail.grad = None
    layer.zero_grad(set_to_none=True)
    keep_casts(layer, True)
    got = layer.forward_tail(torch.cat([x_fixed, tail.detach()], dim=1).bfloat16(), tail)
    got.square().sum().backward()
    assert torch.equal(got, want)
    for g, w in zip((tail.grad, layer.weight.grad, layer.bias.grad), want_grads):
        assert torch.equal(g, w)
    with torch.no_grad():
        layer.weight.add_(1.0)
    assert torch.equal(layer(x), got)  # the kept cast: stale until forgotten
    forget_casts(layer)
    assert torch.equal(layer(x), linear(x, layer.weight, layer.bias, torch.bfloat16))
    assert not torch.equal(layer(x), got)
    keep_casts(layer, False)
    assert layer._low_weight is None
