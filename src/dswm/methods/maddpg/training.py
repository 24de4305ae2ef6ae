"""MADDPG's training loop through the PettingZoo parallel API, on the TRAINING days only.

:func:`parallel_env` builds ``dswm.sim.env.UAVFleetParallelEnv`` on the demand, grid, scenario, initial
deployment and day labels of the training core, so no other day exists in it. Days are visited in shuffled
passes over the training days (a fixed schedule drawn from the seed); each episode is one whole day of
slots_per_day - 1 transitions. The first ``warmup`` transitions act uniformly at random; then every agent acts
with the shared actor on its local view plus Gaussian noise (agent i's view is built from its own observation:
the common maps, fleet and time, and its index, the position of its one-hot in ``possible_agents``). Every
``update_every`` transitions, once the buffer holds a batch, ``gradient_steps`` gradient steps run
(``Learner.update``). A checkpoint (weights,
targets, optimizers, the filled replay, RNG states, counters, history) is written every ``checkpoint_every``
day-episodes and at the end; a run finds it and continues when its settings and inputs are the same.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from dswm.config import ConfigError
from dswm.methods.maddpg.learner import Learner
from dswm.methods.maddpg.networks import N_ACTION, scale_demand
from dswm.methods.maddpg.replay import Replay
from dswm.methods.maddpg.settings import MADDPGSettings
from dswm.sim.env import UAVFleetParallelEnv
from dswm.methods.trained import CurveLog, UnitTrainer, day_schedule
from prep.atomic import atomic_path

METRICS = {"losses/critic": "critic", "losses/actor": "actor", "charts/q_mean": "q",
           "diag/agent_feature_std": "spread"}
"""History names of the gradient-step metrics (means over the window; NaN for a window without a step)."""
EPISODE_METRICS = ("charts/episode_return", "charts/served_ratio")
"""History names of the day-episode metrics: the day's summed team reward and its mean SR_{1..T-1}."""


def parallel_env(core) -> UAVFleetParallelEnv:
    """The PettingZoo parallel environment over the days of ``core`` (a FleetCore of TRAINING days)."""
    t = core.scenario.slots_per_day
    demand = core.demand.detach().cpu().numpy().reshape(core.n_days, t, core.grid.rows, core.grid.cols)
    return UAVFleetParallelEnv(demand=demand, grid=core.grid, scenario=core.scenario,
                               init_pos=core.init_pos.detach().cpu().numpy(), dataset=core.dataset,
                               day_labels=list(core.day_labels))


class Trainer(UnitTrainer):
    """The state of one training run: environment, learner, replay, RNG, counters and history.

    Args:
        core: FleetCore over the TRAINING days; settings: MADDPG's settings; seed: seeds the networks'
            initialization, the day schedule, exploration and batch sampling; device: the networks' device.
    """

    unit = "episode"

    def __init__(self, *, core, settings: MADDPGSettings, seed: int, device: str = "cpu"):
        s, scenario, grid = settings, core.scenario, core.grid
        self.settings, self.scenario, self.grid = s, scenario, grid
        self.per_day = scenario.slots_per_day - 1
        if s.transitions % self.per_day:
            raise ConfigError(f"config key methods.maddpg.transitions: expected whole day-episodes, a multiple of "
                              f"{self.per_day} (slots_per_day - 1), found {s.transitions}")
        self.n_episodes = s.transitions // self.per_day
        self.env = parallel_env(core)
        self.agents = list(self.env.possible_agents)
        self.schedule = day_schedule(core.n_days, self.n_episodes, seed)
        self.device = torch.device(device)
        self.maps = scale_demand(core.demand.reshape(core.n_days, scenario.slots_per_day, grid.rows, grid.cols)
                                 .to(self.device))  # the replay's windows are read from here
        torch.manual_seed(seed)
        self.learner = Learner(settings=s, rows=grid.rows, cols=grid.cols, maps=scenario.obs_window + 1,
                               n_agents=scenario.n_uavs, device=device)
        self.replay = Replay(capacity=min(s.buffer_size, s.transitions), n_agents=scenario.n_uavs)
        self.gen = torch.Generator().manual_seed(seed)  # warm-up actions, exploration noise, batch indices
        self.episode = self.transitions = 0
        self.days_used: list[int] = []
        self.curve = CurveLog((*EPISODE_METRICS, *METRICS), units=self.n_episodes, log_points=s.log_points)

    def _tensor(self, obs: dict) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        return tuple(torch.as_tensor(obs[k], device=self.device).unsqueeze(0) for k in ("demand", "fleet", "time"))

    def _action(self, obs: dict) -> torch.Tensor:
        """(K, 3) the joint action: uniform during warm-up, then the actor's plus Gaussian noise, clipped."""
        k = len(self.agents)
        if self.transitions < self.settings.warmup:
            return torch.rand((k, N_ACTION), generator=self.gen) * 2.0 - 1.0
        mu = self.learner.act(*self._tensor(obs))[0].cpu()
        noise = self.settings.noise_std * torch.randn((k, N_ACTION), generator=self.gen)
        return (mu + noise).clamp(-1.0, 1.0)

    def run_episode(self) -> dict[str, float]:
        """Play the next scheduled day through the parallel API, storing and learning as it goes.

        Returns:
            {"day": core day, "return": summed team reward, "served_ratio": mean SR over the decisions, "updates":
            the metrics of each gradient step (``Learner.update``)}.
        """
        s, first = self.settings, self.agents[0]
        day = int(self.schedule[self.episode])
        obs, _ = self.env.reset(options={"day": day})
        slot, ret, srs, losses = 0, 0.0, [], []
        while self.env.agents:
            own = obs[first]  # the common part of every agent's observation (each adds its one-hot index)
            action = self._action(own)
            nxt, rewards, terminated, truncated, infos = self.env.step(
                {a: action[i].numpy() for i, a in enumerate(self.agents)})
            self.replay.add(day=day, slot=slot, fleet=own["fleet"], time=own["time"], action=action,
                            reward=rewards[first], terminated=terminated[first], truncated=truncated[first],
                            next_fleet=nxt[first]["fleet"], next_time=nxt[first]["time"])
            ret += float(rewards[first])
            srs.append(infos[first]["sr"])
            slot += 1
            self.transitions += 1
            if (self.transitions >= s.warmup and len(self.replay) >= s.batch_size
                    and self.transitions % s.update_every == 0):
                for _ in range(s.gradient_steps):
                    batch = self.learner.inputs(self.replay.sample(s.batch_size, self.gen), self.maps)
                    losses.append(self.learner.update(batch))
            obs = nxt
        if slot != self.per_day:
            raise RuntimeError(f"day {day}: the episode ended after {slot} transitions, expected {self.per_day}")
        self.days_used.append(day)
        self.episode += 1
        self._log(ret, float(np.mean(srs)), losses)
        return {"day": day, "return": ret, "served_ratio": float(np.mean(srs)), "updates": losses}

    def _log(self, ret: float, sr: float, losses: list[dict[str, float]]) -> None:
        self.curve.add("charts/episode_return", ret)
        self.curve.add("charts/served_ratio", sr)
        for name, key in METRICS.items():
            self.curve.add(name, *(m[key] for m in losses))
        self.curve.end_unit(self.episode, self.transitions)

    # ---- checkpoint --------------------------------------------------------------------------------------
    def save(self, path: str | Path, extra: dict) -> None:
        """Write the whole run state atomically (torch.save)."""
        blob = {"learner": self.learner.state_dict(), "replay": self.replay.state_dict(),
                "gen": self.gen.get_state(), "torch_rng": torch.get_rng_state(), "episode": self.episode,
                "transitions": self.transitions, "days_used": list(self.days_used), **self.curve.state_dict(),
                "extra": extra}
        with atomic_path(path) as tmp:
            torch.save(blob, tmp)

    def restore(self, blob: dict) -> None:
        """Continue from what :meth:`save` wrote."""
        self.learner.load_state_dict(blob["learner"])
        self.replay.load_state_dict(blob["replay"])
        self.gen.set_state(blob["gen"])
        torch.set_rng_state(blob["torch_rng"])
        self.episode, self.transitions = int(blob["episode"]), int(blob["transitions"])
        self.days_used = [int(d) for d in blob["days_used"]]
        self.curve.load_state_dict(blob)

