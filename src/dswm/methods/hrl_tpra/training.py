"""HRL-TPRA's training loop on the TRAINING days only.

A round steps ``n_envs`` training days together through the core (one ``FleetCore.step`` per slot), days taken in
order from a fixed schedule of shuffled passes over the training days (drawn from the seed). At slots 0, m, 2m, ...
the planner samples each UAV's target cell; at every slot each resource actor samples its fine move and bandwidth
logit around the move toward its target. After the day (143 decisions) the round's rollout updates both levels
(``learner.Learner.update``). A checkpoint (networks, optimizers, RNG states, counters, days used, history) is
written every ``checkpoint_every`` rounds and at the end; a run finds it and continues when its settings and inputs
are the same.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from dswm.config import ConfigError
from dswm.methods.hrl_tpra.features import Frame, compose_action, low_inputs, plan_inputs
from dswm.methods.hrl_tpra.learner import Learner, Rollout
from dswm.methods.hrl_tpra.settings import HRLTPRASettings
from dswm.methods.trained import CurveLog, UnitTrainer, day_schedule
from prep.atomic import atomic_path

METRICS = {"losses/policy": "policy", "losses/value": "value", "losses/high_policy": "high_policy",
           "losses/high_value": "high_value", "charts/entropy": "entropy", "charts/high_entropy": "high_entropy"}
"""History names of the update metrics (means over the window's rounds)."""
EPISODE_METRICS = ("charts/episode_return", "charts/served_ratio")
"""History names of the day-episode metrics: a day's summed reward and its mean SR_{1..T-1}, over the window."""


class Trainer(UnitTrainer):
    """The state of one training run: core, learner, RNG, counters and history.

    Args:
        core: FleetCore over the TRAINING days; settings: HRL-TPRA's settings; seed: seeds the networks'
            initialization, the day schedule, the planner's and actors' sampling and the minibatches; device.
    """

    unit = "round"

    def __init__(self, *, core, settings: HRLTPRASettings, seed: int, device: str = "cpu"):
        s, scenario = settings, core.scenario
        if s.candidates < scenario.n_uavs:
            raise ConfigError(f"config key methods.hrl_tpra.candidates: expected at least n_uavs = {scenario.n_uavs} "
                              f"(one distinct cell per UAV), found {s.candidates}")
        if s.candidates > core.grid.n_cells:
            raise ConfigError(f"config key methods.hrl_tpra.candidates: expected at most the grid's "
                              f"{core.grid.n_cells} cells, found {s.candidates}")
        self.core, self.settings, self.scenario = core, s, scenario
        self.per_day = scenario.slots_per_day - 1
        self.n_rounds = s.day_episodes // s.n_envs
        self.schedule = day_schedule(core.n_days, s.day_episodes, seed)
        self.device = torch.device(device)
        self.frame = Frame.of(core.grid, scenario, self.device)
        torch.manual_seed(seed)
        self.learner = Learner(settings=s, n_uavs=scenario.n_uavs, device=device)
        self.gen = torch.Generator().manual_seed(seed)  # planner and actor sampling, minibatch order
        self.round = 0
        self.days_used: list[int] = []
        self.curve = CurveLog((*EPISODE_METRICS, *METRICS), units=self.n_rounds, log_points=s.log_points)

    @property
    def transitions(self) -> int:
        return self.per_day * len(self.days_used)

    def _tensors(self, obs: dict) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        return tuple(torch.as_tensor(obs[k], device=self.device) for k in ("demand", "fleet", "time"))

    def collect(self, days: np.ndarray) -> tuple[Rollout, np.ndarray]:
        """Play the core days ``days`` (E,) for one whole day with the sampling policies.

        Returns:
            the rollout and (E,) the mean served ratio of each day's decisions.
        """
        s, net, frame = self.settings, self.learner, self.frame
        m, t_max = s.macro_slots, self.per_day
        obs = self.core.reset(days)
        low: dict[str, list] = {k: [] for k in ("local", "glob", "action", "logp", "value", "active", "reward")}
        high: dict[str, list] = {k: [] for k in ("cand", "uav", "dist", "summary", "choice", "plan_logp",
                                                 "plan_value", "macro_reward")}
        srs = []
        with torch.no_grad():
            for t in range(t_max + 1):
                demand, fleet, time = self._tensors(obs)
                if t % m == 0 or t == t_max:
                    plan = plan_inputs(demand, fleet, time, frame, s.candidates)
                    if t == t_max:  # o_143: the day's end truncates, both levels bootstrap on it
                        plan_last_value = net.plan_critic(plan.summary)
                    else:
                        choice = net.planner(plan.cand, plan.uav, plan.dist, generator=self.gen)
                        target = plan.cells.gather(1, choice.choice)
                        for key, v in (("cand", plan.cand), ("uav", plan.uav), ("dist", plan.dist),
                                       ("summary", plan.summary), ("choice", choice.choice),
                                       ("plan_logp", choice.logp), ("plan_value", net.plan_critic(plan.summary))):
                            high[key].append(v)
                        high["macro_reward"].append(torch.zeros(len(days), device=self.device))
                phase = torch.full((len(days),), (t % m) / m, device=self.device)
                local, glob = low_inputs(demand, fleet, time, target, phase, frame, s.crop_radius)
                value = net.actors.value(local, glob)
                if t == t_max:
                    last_value = value
                    break
                mean = net.actors.mean(local)
                raw = net.actors.sample(mean, self.gen)
                action = compose_action(raw.clamp(-1.0, 1.0), fleet, target, frame, s.fine_scale)
                out = self.core.step(action.cpu().numpy())
                reward = torch.as_tensor(out.reward, dtype=torch.float32, device=self.device)
                for key, v in (("local", local), ("glob", glob), ("action", raw),
                               ("logp", net.actors.log_prob(mean, raw)), ("value", value),
                               ("active", fleet[..., 3] > 0.5), ("reward", reward)):
                    low[key].append(v)
                high["macro_reward"][-1] += reward
                srs.append(out.sr)
                obs = out.obs
        ro = Rollout(**{k: torch.stack(v) for k, v in {**low, **high}.items()}, last_value=last_value,
                     plan_last_value=plan_last_value)
        return ro, np.mean(np.stack(srs), axis=0)

    def run_round(self) -> dict:
        """Collect the next ``n_envs`` scheduled days and update both levels.

        Returns:
            {"days": core days, "return": mean summed reward of the days, "served_ratio": their mean SR, "update":
            the round's mean losses (``Learner.update``)}.
        """
        s = self.settings
        days = self.schedule[self.round * s.n_envs:(self.round + 1) * s.n_envs]
        ro, sr = self.collect(days)
        update = self.learner.update(ro, self.gen)
        self.days_used += [int(d) for d in days]
        self.round += 1
        ret = float(ro.reward.sum(0).mean())
        self._log(ret, float(sr.mean()), update)
        return {"days": [int(d) for d in days], "return": ret, "served_ratio": float(sr.mean()), "update": update}

    def _log(self, ret: float, sr: float, update: dict[str, float]) -> None:
        self.curve.add("charts/episode_return", ret)
        self.curve.add("charts/served_ratio", sr)
        for name, key in METRICS.items():
            self.curve.add(name, update[key])
        self.curve.end_unit(self.round, self.transitions)

    # ---- checkpoint --------------------------------------------------------------------------------------
    def save(self, path: str | Path, extra: dict) -> None:
        """Write the whole run state atomically (torch.save)."""
        blob = {"learner": self.learner.state_dict(), "gen": self.gen.get_state(),
                "torch_rng": torch.get_rng_state(), "round": self.round, "days_used": list(self.days_used),
                **self.curve.state_dict(), "extra": extra}
        with atomic_path(path) as tmp:
            torch.save(blob, tmp)

    def restore(self, blob: dict) -> None:
        """Continue from what :meth:`save` wrote."""
        self.learner.load_state_dict(blob["learner"])
        self.gen.set_state(blob["gen"])
        torch.set_rng_state(blob["torch_rng"])
        self.round = int(blob["round"])
        self.days_used = [int(d) for d in blob["days_used"]]
        self.curve.load_state_dict(blob)
