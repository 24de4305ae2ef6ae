"""MADDPG's networks and gradient step (Lowe et al. 2017, Algorithm 1, with deterministic continuous actions).

Per gradient step, on a replayed batch of joint transitions (x, a, r, x'):

1. Critic: y = r + gamma (1 - terminated) Q'(x', mu'(o'_1), ..., mu'(o'_K)); minimize (Q(x, a) - y)^2. The day's
   end only truncates an episode (``terminated`` is always False in this environment), so y bootstraps there.
2. Actor (shared): maximize, for every agent i, Q(x, a_1, ..., mu(o_i), ..., a_K) with the OTHER agents' actions
   taken from the replay, as in the paper's policy gradient; plus ``action_reg`` times the mean squared pre-tanh
   output (Lowe et al.'s regularizer of the policy's outputs).
3. Targets: Polyak averaging with rate tau.

The team reward is shared, so the K critics Q_i of the paper have identical targets; they are one network here.
Every network computes its matrix products in ``matmul_dtype`` (:mod:`dswm.methods.matmul`); the optimizers are
torch's fused Adam, the Polyak step one ``torch._foreach_lerp_`` per network.
"""
from __future__ import annotations

import copy
from typing import NamedTuple

import torch

from dswm.methods.maddpg.networks import (CentralCritic, SharedActor, agent_spread, joint_dim, joint_observation,
                                          local_dim, local_observation, scale_demand)
from dswm.methods.maddpg.replay import window_maps
from dswm.methods.maddpg.settings import MADDPGSettings
from dswm.methods.matmul import MATMUL_DTYPES


class Inputs(NamedTuple):
    """A replayed batch as the networks read it."""

    local: torch.Tensor  # (N, K, local_dim) o_1..o_K
    joint: torch.Tensor  # (N, joint_dim) x
    action: torch.Tensor  # (N, K, 3)
    reward: torch.Tensor  # (N,)
    terminated: torch.Tensor  # (N,) float 0/1
    next_local: torch.Tensor  # (N, K, local_dim) o'_1..o'_K
    next_joint: torch.Tensor  # (N, joint_dim) x'


class Learner:
    """Actor, critic, their targets and optimizers for a fleet of ``n_agents`` UAVs on an R x C grid.

    Args:
        settings: network sizes and optimization settings.
        rows, cols: the grid; maps: w+1 demand maps per observation; n_agents: K.
        device: torch device of the networks.
    """

    def __init__(self, *, settings: MADDPGSettings, rows: int, cols: int, maps: int, n_agents: int,
                 device: str = "cpu"):
        self.settings, self.maps, self.device = settings, maps, torch.device(device)
        s = settings
        self.dtype = MATMUL_DTYPES[s.matmul_dtype]
        self.actor = SharedActor(n_agents=n_agents, obs_dim=local_dim(maps, s.crop_radius), embed=s.index_embed,
                                 hidden=s.actor_hidden, depth=s.actor_depth, crop=(maps + 1, 2 * s.crop_radius + 1),
                                 matmul_dtype=s.matmul_dtype).to(self.device)
        self.critic = CentralCritic(obs_dim=joint_dim(maps, rows, cols, n_agents), n_agents=n_agents,
                                    hidden=s.critic_hidden, depth=s.critic_depth, matmul_dtype=s.matmul_dtype
                                    ).to(self.device)
        self.target_actor = copy.deepcopy(self.actor).requires_grad_(False)
        self.target_critic = copy.deepcopy(self.critic).requires_grad_(False)
        self.actor_opt = torch.optim.Adam(self.actor.parameters(), lr=s.actor_lr, fused=True)
        self.critic_opt = torch.optim.Adam(self.critic.parameters(), lr=s.critic_lr, fused=True)
        self._polyak = [(list(net.parameters()), list(target.parameters()))
                        for net, target in ((self.actor, self.target_actor), (self.critic, self.target_critic))]
        self.steps = 0
        self._maps: tuple[torch.Tensor, torch.Tensor] | None = None

    # ---- acting ------------------------------------------------------------------------------------------
    def local(self, maps: torch.Tensor, fleet: torch.Tensor, time: torch.Tensor) -> torch.Tensor:
        """(N, K, local_dim) local observations of scaled maps (see ``networks.local_observation``)."""
        return local_observation(maps, fleet, time, self.settings.crop_radius)

    @torch.no_grad()
    def act(self, demand: torch.Tensor, fleet: torch.Tensor, time: torch.Tensor) -> torch.Tensor:
        """(N, K, 3) deterministic actions tanh(mu(o_k)) in [-1, 1] for observations (raw demand) with a leading
        axis N."""
        pre, _ = self.actor(self.local(scale_demand(demand), fleet, time))
        return torch.tanh(pre)

    # ---- gradient step -----------------------------------------------------------------------------------
    def inputs(self, batch: dict[str, torch.Tensor], maps: torch.Tensor) -> Inputs:
        """A replayed batch (``Replay.sample``) with its windows read from ``maps`` (D, T, R, C), the training
        days' SCALED demand (``networks.scale_demand``); the observations in the products' dtype (they enter the
        networks' first layers only)."""
        b = {k: v.to(self.device) for k, v in batch.items()}
        if self._maps is None or self._maps[0] is not maps:  # rounded once to the products' dtype, as they would be
            self._maps = (maps, maps.to(self.dtype))
        maps = self._maps[1]
        now = window_maps(maps, b["day"], b["slot"], self.maps)
        nxt = window_maps(maps, b["day"], b["slot"] + 1, self.maps)
        return Inputs(local=self.local(now, b["fleet"], b["time"]).to(self.dtype),
                      joint=joint_observation(now, b["fleet"], b["time"]).to(self.dtype), action=b["action"],
                      reward=b["reward"], terminated=b["terminated"].float(),
                      next_local=self.local(nxt, b["next_fleet"], b["next_time"]).to(self.dtype),
                      next_joint=joint_observation(nxt, b["next_fleet"], b["next_time"]).to(self.dtype))

    @torch.no_grad()
    def td_target(self, x: Inputs) -> torch.Tensor:
        """(N,) y = r + gamma (1 - terminated) Q'(x', mu'(o')): a truncated transition bootstraps."""
        next_action = torch.tanh(self.target_actor(x.next_local)[0])
        return x.reward + self.settings.gamma * (1.0 - x.terminated) * self.target_critic(x.next_joint, next_action)

    def critic_loss(self, x: Inputs) -> torch.Tensor:
        """Mean squared TD error of the critic on ``x``."""
        return torch.mean((self.critic(x.joint, x.action) - self.td_target(x)) ** 2)

    def update(self, x: Inputs) -> dict[str, float]:
        """One gradient step of the critic, then of the actor, then the targets' Polyak step.

        Returns:
            {"critic": TD loss, "actor": actor loss, "q": mean Q(x, a), "spread": cross-agent feature std}
        """
        s = self.settings
        # Critic
        q = self.critic(x.joint, x.action)
        critic_loss = torch.mean((q - self.td_target(x)) ** 2)
        self.critic_opt.zero_grad(set_to_none=True)
        critic_loss.backward()
        torch.nn.utils.clip_grad_norm_(self.critic.parameters(), s.grad_clip, foreach=True)
        self.critic_opt.step()
        # Actor: agent i's action from the current policy, the others' from the replay
        pre, feats = self.actor(x.local)
        self.critic.requires_grad_(False)  # the actor's loss differentiates through Q, not into it
        q_i = self.critic.substituted(x.joint, x.action, torch.tanh(pre))  # (N, K)
        actor_loss = -q_i.mean() + s.action_reg * (pre ** 2).mean()
        self.actor_opt.zero_grad(set_to_none=True)
        actor_loss.backward()
        self.critic.requires_grad_(True)
        torch.nn.utils.clip_grad_norm_(self.actor.parameters(), s.grad_clip, foreach=True)
        self.actor_opt.step()
        # Targets
        with torch.no_grad():
            for params, targets in self._polyak:
                torch._foreach_lerp_(targets, params, s.tau)
        self.steps += 1
        return {"critic": critic_loss.item(), "actor": actor_loss.item(), "q": q.detach().mean().item(),
                "spread": agent_spread(feats.detach()).item()}

    # ---- state -------------------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        """Weights, target weights, optimizer states and the gradient-step count."""
        return {"actor": self.actor.state_dict(), "critic": self.critic.state_dict(),
                "target_actor": self.target_actor.state_dict(), "target_critic": self.target_critic.state_dict(),
                "actor_opt": self.actor_opt.state_dict(), "critic_opt": self.critic_opt.state_dict(),
                "steps": self.steps}

    def load_state_dict(self, state: dict) -> None:
        for name in ("actor", "critic", "target_actor", "target_critic", "actor_opt", "critic_opt"):
            getattr(self, name).load_state_dict(state[name])
        self.steps = int(state["steps"])
