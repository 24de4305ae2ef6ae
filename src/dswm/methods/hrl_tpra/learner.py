"""HRL-TPRA's targets and gradient steps: PPO with GAE for the resource actors, clipped policy gradient with a
learned baseline for the pointer planner.

* Low level: per UAV, GAE(gamma, lambda) on the team reward with that UAV's critic. A rollout is whole days; the
  day's end TRUNCATES, so the last step bootstraps on the critics' value of o_143 (:func:`gae`). The clipped
  policy loss counts only UAVs that were active at the step (the others' moves do nothing).
* High level: a macro-slot's decision is scored by its summed reward plus ``high_gamma`` times the planner
  critic's value at the next macro-slot's start (at the day's end, of o_143: truncation again), minus the
  baseline V(s) (:func:`macro_targets`); with high_gamma = 0 this is REINFORCE with a baseline on the
  macro-slot's summed reward. The log-probability of a stored assignment is the pointer's, teacher-forced.
"""
from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np
import torch
from torch import nn

from dswm.methods.hrl_tpra.actors import ResourceActors
from dswm.methods.hrl_tpra.features import local_dim, summary_dim
from dswm.methods.hrl_tpra.pointer import PlanCritic, PointerPlanner
from dswm.methods.hrl_tpra.settings import HRLTPRASettings


def gae(reward: torch.Tensor, value: torch.Tensor, last_value: torch.Tensor, terminated: torch.Tensor,
        gamma: float, lam: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Generalized advantage estimates of one rollout of whole days, per UAV.

    Args:
        reward: (T, E) team rewards; value: (T, E, K) each UAV's critic at o_t; last_value: (E, K) at o_T, the
            observation after the last step (the day's end truncates: it is bootstrapped on).
        terminated: (T, E) bool, True where a step ended the task (nothing is bootstrapped past it).

    Returns:
        advantages (T, E, K) and value targets (T, E, K) = advantages + value.
    """
    adv = torch.zeros_like(value)
    running = torch.zeros_like(last_value)
    next_value = last_value
    for t in range(reward.shape[0] - 1, -1, -1):
        live = (~terminated[t]).to(value.dtype).unsqueeze(-1)
        delta = reward[t].unsqueeze(-1) + gamma * live * next_value - value[t]
        running = delta + gamma * lam * live * running
        adv[t] = running
        next_value = value[t]
    return adv, adv + value


def macro_targets(reward: torch.Tensor, value: torch.Tensor, last_value: torch.Tensor, terminated: torch.Tensor,
                  high_gamma: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Advantages and value targets of the planner's M macro decisions per day.

    Args:
        reward: (M, E) summed reward of each macro-slot; value: (M, E) the planner critic at its start;
        last_value: (E,) at the day's last observation; terminated: (M, E) bool.

    Returns:
        (advantage, target), each (M, E): target = reward + high_gamma * V(next start), advantage = target - value.
    """
    nxt = torch.cat([value[1:], last_value.unsqueeze(0)], dim=0)
    target = reward + high_gamma * (~terminated).to(value.dtype) * nxt
    return target - value, target


@dataclasses.dataclass
class Rollout:
    """One round of E whole days: T = 143 low-level steps and M macro decisions per day."""

    local: torch.Tensor      # (T, E, K, D)
    glob: torch.Tensor       # (T, E, G)
    action: torch.Tensor     # (T, E, K, 3) raw Gaussian samples
    logp: torch.Tensor       # (T, E, K)
    value: torch.Tensor      # (T, E, K)
    active: torch.Tensor     # (T, E, K) bool
    reward: torch.Tensor     # (T, E)
    last_value: torch.Tensor  # (E, K)
    cand: torch.Tensor       # (M, E, N, F)
    uav: torch.Tensor        # (M, E, K, 7)
    dist: torch.Tensor       # (M, E, K, N)
    summary: torch.Tensor    # (M, E, S)
    choice: torch.Tensor     # (M, E, K)
    plan_logp: torch.Tensor  # (M, E)
    plan_value: torch.Tensor  # (M, E)
    macro_reward: torch.Tensor  # (M, E)
    plan_last_value: torch.Tensor  # (E,)


class Losses(NamedTuple):
    """The scalar losses of one minibatch of one level."""

    policy: torch.Tensor
    value: torch.Tensor
    entropy: torch.Tensor


def _normalized(adv: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    sel = adv[mask] if mask is not None else adv
    if sel.numel() < 2:
        return adv - sel.mean() if sel.numel() else adv
    return (adv - sel.mean()) / (sel.std() + 1e-8)


def _clipped(ratio: torch.Tensor, adv: torch.Tensor, clip: float) -> torch.Tensor:
    return -torch.min(ratio * adv, ratio.clamp(1.0 - clip, 1.0 + clip) * adv)


class Learner:
    """The planner, the resource actors, their critics and optimizers.

    Args:
        settings: HRL-TPRA's settings; n_uavs: K; device: the networks' device.
    """

    def __init__(self, *, settings: HRLTPRASettings, n_uavs: int, device: str = "cpu"):
        s = settings
        self.settings, self.device = s, torch.device(device)
        self.planner = PointerPlanner(n_uavs=n_uavs, hidden=s.pointer_hidden, tanh_clip=s.tanh_clip).to(self.device)
        self.plan_critic = PlanCritic(in_dim=summary_dim(s.candidates, n_uavs), hidden=s.pointer_hidden).to(self.device)
        self.actors = ResourceActors(n_uavs=n_uavs, in_dim=local_dim(s.crop_radius), hidden=s.actor_hidden,
                                     depth=s.actor_depth, log_std_init=s.log_std_init).to(self.device)
        self.optimizers = {
            "actor": torch.optim.Adam(self.actors.actor_parameters(), lr=s.lr),
            "critic": torch.optim.Adam(self.actors.critic.parameters(), lr=s.lr),
            "planner": torch.optim.Adam(self.planner.parameters(), lr=s.high_lr),
            "plan_critic": torch.optim.Adam(self.plan_critic.parameters(), lr=s.high_lr)}
        self.steps = 0

    # ---- losses --------------------------------------------------------------------------------------------
    def low_losses(self, local, glob, action, old_logp, adv, target, active) -> Losses:
        """PPO losses of the resource actors on a minibatch of day-slots (each holds the K UAVs)."""
        logp = self.actors.log_prob(self.actors.mean(local), action)
        ratio = torch.exp(logp - old_logp)
        mask = active.to(logp.dtype)
        per_uav = _clipped(ratio, _normalized(adv, active), self.settings.clip_range)
        policy = (per_uav * mask).sum() / mask.sum().clamp(min=1.0)  # the inactive UAVs' moves do nothing
        value = (self.actors.value(local, glob) - target).pow(2).mean()
        return Losses(policy, value, self.actors.entropy().mean())

    def high_losses(self, cand, uav, dist, summary, choice, old_logp, adv, target) -> Losses:
        """Clipped policy-gradient and baseline losses of the planner on a batch of macro decisions."""
        plan = self.planner(cand, uav, dist, choice=choice)
        ratio = torch.exp(plan.logp - old_logp)
        policy = _clipped(ratio, _normalized(adv), self.settings.clip_range).mean()
        value = (self.plan_critic(summary) - target).pow(2).mean()
        return Losses(policy, value, plan.entropy.mean())

    def critic_loss(self, ro: Rollout) -> float:
        """Mean squared error of the resource critics against a rollout's discounted returns to the day's end (GAE
        with lambda = 1, bootstrapped on o_143), a target that does not move with the critics (no gradient)."""
        with torch.no_grad():
            _, target = gae(ro.reward, ro.value, ro.last_value, torch.zeros_like(ro.reward, dtype=torch.bool),
                            self.settings.gamma, 1.0)
            t, e = ro.reward.shape
            value = self.actors.value(ro.local.flatten(0, 1), ro.glob.flatten(0, 1)).view(t, e, -1)
            return float((value - target).pow(2).mean())

    def plan_critic_loss(self, ro: Rollout) -> float:
        """Mean squared error of the planner's critic against a rollout's macro returns to the day's end (summed
        macro rewards discounted by high_gamma, bootstrapped on o_143; no gradient)."""
        with torch.no_grad():
            target = torch.zeros_like(ro.macro_reward)
            running = ro.plan_last_value
            for m in range(ro.macro_reward.shape[0] - 1, -1, -1):
                running = ro.macro_reward[m] + self.settings.high_gamma * running
                target[m] = running
            return float((self.plan_critic(ro.summary.flatten(0, 1)).view_as(target) - target).pow(2).mean())

    # ---- one round's update --------------------------------------------------------------------------------
    def _step(self, names: tuple[str, str], policy_loss, value_loss, nets: tuple[list, list]) -> None:
        for name in names:
            self.optimizers[name].zero_grad(set_to_none=True)
        (policy_loss + value_loss).backward()  # the two networks share no parameter
        for name, params in zip(names, nets):
            nn.utils.clip_grad_norm_(params, self.settings.max_grad_norm)
            self.optimizers[name].step()
        self.steps += 1

    def update(self, ro: Rollout, generator: torch.Generator) -> dict[str, float]:
        """``n_epochs`` passes of minibatches of day-slots for the actors, then ``high_epochs`` passes of minibatches
        of macro decisions for the planner. Returns the mean of each loss over the round's steps."""
        s = self.settings
        no_end = torch.zeros_like(ro.reward, dtype=torch.bool)  # a day's end truncates: nothing terminates
        adv, target = gae(ro.reward, ro.value, ro.last_value, no_end, s.gamma, s.gae_lambda)
        hadv, htarget = macro_targets(ro.macro_reward, ro.plan_value, ro.plan_last_value,
                                      torch.zeros_like(ro.macro_reward, dtype=torch.bool), s.high_gamma)
        low = [x.flatten(0, 1) for x in (ro.local, ro.glob, ro.action, ro.logp, adv, target, ro.active)]
        high = [x.flatten(0, 1) for x in (ro.cand, ro.uav, ro.dist, ro.summary, ro.choice, ro.plan_logp, hadv,
                                           htarget)]
        logs: dict[str, list[float]] = {k: [] for k in ("policy", "value", "entropy", "high_policy", "high_value",
                                                        "high_entropy")}
        n, n_high = low[0].shape[0], high[0].shape[0]
        actor_params, critic_params = self.actors.actor_parameters(), list(self.actors.critic.parameters())
        planner_params, plan_critic_params = list(self.planner.parameters()), list(self.plan_critic.parameters())
        for _ in range(s.n_epochs):
            order = torch.randperm(n, generator=generator).to(self.device)
            for start in range(0, n, s.batch_size):
                idx = order[start:start + s.batch_size]
                lo = self.low_losses(*(x[idx] for x in low))
                self._step(("actor", "critic"), lo.policy - s.ent_coef * lo.entropy, lo.value,
                           (actor_params, critic_params))
                for key, v in zip(("policy", "value", "entropy"), lo):
                    logs[key].append(float(v.detach()))
        for _ in range(s.high_epochs):
            order = torch.randperm(n_high, generator=generator).to(self.device)
            for start in range(0, n_high, s.high_batch_size):
                idx = order[start:start + s.high_batch_size]
                hi = self.high_losses(*(x[idx] for x in high))
                self._step(("planner", "plan_critic"), hi.policy - s.high_ent_coef * hi.entropy, hi.value,
                           (planner_params, plan_critic_params))
                for key, v in zip(("high_policy", "high_value", "high_entropy"), hi):
                    logs[key].append(float(v.detach()))
        return {k: float(np.mean(v)) for k, v in logs.items()}

    # ---- state ---------------------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {"planner": self.planner.state_dict(), "plan_critic": self.plan_critic.state_dict(),
                "actors": self.actors.state_dict(), "steps": self.steps,
                "optimizers": {k: o.state_dict() for k, o in self.optimizers.items()}}

    def load_state_dict(self, state: dict) -> None:
        self.planner.load_state_dict(state["planner"])
        self.plan_critic.load_state_dict(state["plan_critic"])
        self.actors.load_state_dict(state["actors"])
        for k, o in self.optimizers.items():
            o.load_state_dict(state["optimizers"][k])
        self.steps = int(state["steps"])
