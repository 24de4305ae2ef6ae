"""GA-MATR's training loop on the TRAINING days: rounds of whole day-episodes, each followed by a HAPPO update.

A round steps ``n_envs`` training days together through ONE ``FleetCore`` (the train rule's core, which holds the
training days only), 143 decisions each, with actions sampled from the shared Gaussian policy (unclipped samples
kept for the log-probabilities, clipped to [-1, 1] for the environment). The days come from a fixed schedule
drawn from the seed: shuffled passes over the training days (``dswm.methods.trained.day_schedule``). After each
step the learner's reward is the environment's eq. 7 minus ``fairness_weight`` times the coefficient of variation (population std /
mean) of the served load of the UAVs available in the slot (``FleetCore.uav_load``, :func:`load_cv`);
the history keeps the environment's return apart. The day's end truncates: GAE bootstraps V(o_143) there.
A checkpoint (weights, optimizers, value normalizer, the generator's state, counters, history) is written every
``checkpoint_every`` rounds and at the end; a run finds it and continues when its settings and inputs are the same.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from dswm.config import ConfigError
from dswm.methods.ga_matr.happo import Learner, Rollout, gae
from dswm.methods.ga_matr.networks import ACTIVE_FEATURE, PolicyInputs, context_dim, policy_inputs, uav_dim
from dswm.methods.ga_matr.settings import GAMATRSettings
from dswm.methods.rl.spaces import flat_observation, observation_dim
from dswm.methods.trained import CurveLog, UnitTrainer, day_schedule
from prep.atomic import atomic_path

METRICS = {"losses/policy": "policy", "losses/value": "value", "charts/entropy": "entropy",
           "charts/approx_kl": "approx_kl", "charts/clip_fraction": "clip_fraction",
           "charts/happo_factor_std": "factor_std", "diag/agent_embedding_std": "embedding_std"}
"""History names of the update's metrics (``Learner.update``), means over the window of rounds."""
ROUND_METRICS = ("charts/episode_return", "charts/learner_return", "charts/served_ratio", "charts/load_cv")
"""History names of the rounds' metrics: a day's summed eq.-7 reward, the same with the fairness term taken off,
the mean SR over its decisions, and the mean coefficient of variation of the UAVs' served load per slot."""


def load_cv(load: np.ndarray, available: np.ndarray) -> np.ndarray:
    """(B,) population std / mean of the served load (B, K) over the available UAVs (B, K) bool; 0 where fewer
    than two are available or they served nothing."""
    avail = available.astype(np.float64)
    count = avail.sum(axis=1)
    mean = (load * avail).sum(axis=1) / np.maximum(count, 1.0)
    std = np.sqrt((((load - mean[:, None]) ** 2) * avail).sum(axis=1) / np.maximum(count, 1.0))
    ok = (count >= 2) & (mean > 0)
    return np.where(ok, std / np.where(ok, mean, 1.0), 0.0)


class Trainer(UnitTrainer):
    """The state of one training run: core, learner, generator, counters and history.

    Args:
        core: FleetCore over the TRAINING days; settings: GA-MATR's settings; seed: seeds the networks'
            initialization, the day schedule, the action noise, the agents' order and the minibatches;
            device: the networks' device.
    """

    unit = "round"

    def __init__(self, *, core, settings: GAMATRSettings, seed: int, device: str = "cpu"):
        s, scenario, grid = settings, core.scenario, core.grid
        self.core, self.settings = core, s
        self.per_day = scenario.slots_per_day - 1
        per_round = self.per_day * s.n_envs
        if s.transitions % per_round:
            raise ConfigError(f"config key methods.ga_matr.transitions: expected whole rounds, a multiple of "
                              f"{per_round} (n_envs x (slots_per_day - 1)), found {s.transitions}")
        self.n_rounds = s.transitions // per_round
        self.schedule = day_schedule(core.n_days, self.n_rounds * s.n_envs, seed).reshape(self.n_rounds, s.n_envs)
        self.device = torch.device(device)
        maps = scenario.obs_window + 1
        torch.manual_seed(seed)
        self.learner = Learner(settings=s, n_agents=scenario.n_uavs, uav_in=uav_dim(maps, s.crop_radius),
                               context_in=context_dim(maps), obs_dim=observation_dim(grid.rows, grid.cols, scenario),
                               device=device)
        self.gen = torch.Generator().manual_seed(seed)
        self.round = self.transitions = 0
        self.days_used: list[int] = []
        self.curve = CurveLog((*ROUND_METRICS, *METRICS), units=self.n_rounds, log_points=s.log_points)

    def observe(self, obs: dict) -> tuple[PolicyInputs, torch.Tensor]:
        """The policy's inputs and the critic's flat observation of a batched observation (numpy)."""
        demand, fleet, t = (torch.as_tensor(obs[k], device=self.device) for k in ("demand", "fleet", "time"))
        x = policy_inputs(demand, fleet, t, radius=self.settings.crop_radius, side=self.settings.context_side)
        return x, torch.as_tensor(flat_observation(obs), device=self.device)

    def collect(self, days: np.ndarray) -> tuple[Rollout, dict[str, float]]:
        """Play the core days ``days`` together with the sampling policy; the rollout and its statistics."""
        s, learner = self.settings, self.learner
        obs = self.core.reset(days)
        steps: dict[str, list] = {k: [] for k in ("inputs", "critic", "action", "logp", "value", "reward", "term")}
        env_return, served, cv = np.zeros(len(days)), np.zeros(len(days)), np.zeros(len(days))
        for t in range(self.per_day):
            x, c = self.observe(obs)
            action, logp = learner.sample(x, self.gen)
            out = self.core.step(action.clamp(-1.0, 1.0).cpu().numpy())
            if bool(out.truncated.any()) != (t == self.per_day - 1) or out.terminated.any():
                raise RuntimeError(f"days {days.tolist()}: unexpected episode end at decision {t}")
            imbalance = load_cv(self.core.uav_load, out.obs["fleet"][..., ACTIVE_FEATURE] > 0.5)
            reward = out.reward - s.fairness_weight * imbalance
            for key, value in (("inputs", x), ("critic", c), ("action", action), ("logp", logp),
                               ("value", learner.value(c))):
                steps[key].append(value)
            steps["reward"].append(torch.as_tensor(reward, dtype=torch.float32))
            steps["term"].append(torch.as_tensor(out.terminated))
            env_return += out.reward
            served += out.sr
            cv += imbalance
            obs = out.obs
        last_value = learner.value(self.observe(obs)[1])  # V(o_143): the day's end truncates, bootstrap it
        rewards = torch.stack(steps["reward"]).to(self.device)
        adv, ret = gae(rewards, torch.stack(steps["value"]), last_value, torch.stack(steps["term"]).to(self.device),
                       gamma=s.gamma, lam=s.gae_lambda)
        inputs = PolicyInputs(*(torch.cat([x[i] for x in steps["inputs"]]) for i in range(len(PolicyInputs._fields))))
        rollout = Rollout(inputs=inputs, critic_obs=torch.cat(steps["critic"]), action=torch.cat(steps["action"]),
                          old_logp=torch.cat(steps["logp"]), advantage=adv.flatten(), returns=ret.flatten())
        stats = {"charts/episode_return": float(env_return.mean()),
                 "charts/learner_return": float(rewards.sum(0).mean()),
                 "charts/served_ratio": float(served.mean() / self.per_day),
                 "charts/load_cv": float(cv.mean() / self.per_day)}
        return rollout, stats

    def run_round(self, trace: list | None = None) -> dict:
        """Collect the next scheduled round and update on it.

        Returns:
            {"days": the round's core days, **the round's statistics, "update": ``Learner.update``'s metrics}.
        """
        days = self.schedule[self.round]
        rollout, stats = self.collect(days)
        update = self.learner.update(rollout, self.gen, trace)
        self.days_used.extend(int(d) for d in days)
        self.transitions += self.per_day * len(days)
        self.round += 1
        self._log(stats, update)
        return {"days": days.tolist(), **stats, "update": update}

    def _log(self, stats: dict[str, float], update: dict) -> None:
        for name in ROUND_METRICS:
            self.curve.add(name, stats[name])
        for name, key in METRICS.items():
            self.curve.add(name, update[key])
        self.curve.end_unit(self.round, self.transitions)

    # ---- checkpoint --------------------------------------------------------------------------------------
    def save(self, path: str | Path, extra: dict) -> None:
        """Write the whole run state atomically (torch.save); rounds start from a reset core, so no env state."""
        blob = {"learner": self.learner.state_dict(), "gen": self.gen.get_state(), "round": self.round,
                "transitions": self.transitions, "days_used": list(self.days_used), **self.curve.state_dict(),
                "extra": extra}
        with atomic_path(path) as tmp:
            torch.save(blob, tmp)

    def restore(self, blob: dict) -> None:
        """Continue from what :meth:`save` wrote."""
        self.learner.load_state_dict(blob["learner"])
        self.gen.set_state(blob["gen"])
        self.round, self.transitions = int(blob["round"]), int(blob["transitions"])
        self.days_used = [int(d) for d in blob["days_used"]]
        self.curve.load_state_dict(blob)

