"""GA-MATR's learner: GAE with bootstrapping at the day's end, and HAPPO's sequential per-agent trust-region update.

Per update, on one rollout of N joint transitions (Kuba et al. 2022, HAPPO, with the shared policy of
:mod:`.networks`):

1. Advantages: A = GAE(gamma, lambda) of the team reward the learner sees (eq. 7 minus the fairness term) with a
   centralized V(s); the day's end TRUNCATES, so the last step's target bootstraps gamma V(o_143)
   (:func:`gae`), then A is normalized over the rollout. Every agent shares A (one team reward).
2. Agents one by one in a permutation drawn from the learner's generator. The weight of agent m's surrogate is
   M = prod of pi_new / pi_old of the agents updated before it (each ratio taken right after that agent's own
   update and held fixed, 1 for a sample where that agent was unavailable: its action does nothing then);
   agent m maximizes E[min(r_m M A, clip(r_m, 1 - eps, 1 + eps) M A)] (:func:`happo_surrogate`) plus its
   entropy bonus over ``epochs`` passes of ``minibatches`` minibatches, through its own log-probabilities only.
   Its samples where it was unavailable are left out. Then M *= r_m (new policy).
   The policy's parameters are shared, so agent m's step also moves the other agents' policies; HAPPO's factor
   still holds each agent's ratio as it was right after its own step, as an implementation of HAPPO with
   parameter sharing does.
3. Critic: ``critic_epochs`` passes of mean squared error to the returns A_raw + V_old in normalized units
   (:class:`ValueNorm`, running mean and std of every return seen).
"""
from __future__ import annotations

from typing import NamedTuple

import torch

from dswm.methods.ga_matr.networks import (CentralCritic, GraphAttentionPolicy, PolicyInputs,
                                           agent_embedding_std, entropy, log_prob)
from dswm.methods.ga_matr.settings import GAMATRSettings


class Rollout(NamedTuple):
    """One rollout flattened to N joint transitions (slot-major: row t * n_envs + e)."""

    inputs: PolicyInputs  # the policy's inputs of o_t
    critic_obs: torch.Tensor  # (N, D) flat global observation o_t
    action: torch.Tensor  # (N, K, 3) unclipped Gaussian samples
    old_logp: torch.Tensor  # (N, K) their log-probabilities under the acting policy
    advantage: torch.Tensor  # (N,) GAE advantages (raw)
    returns: torch.Tensor  # (N,) A + V_old, the critic's targets (raw units)


def gae(rewards: torch.Tensor, values: torch.Tensor, last_value: torch.Tensor, terminated: torch.Tensor, *,
        gamma: float, lam: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Generalized advantage estimation over a rollout of whole episodes.

    Args:
        rewards, values, terminated: (T, E) reward of step t, V(o_t), and whether step t ended the episode by a
            terminal state (then nothing is bootstrapped). A step that only truncates (the day's end) is not
            terminated: its target bootstraps.
        last_value: (E,) V of the observation after the last step (o_T), bootstrapped at the truncation.
        gamma, lam: discount and GAE lambda.

    Returns:
        (advantages (T, E), returns = advantages + values (T, E)).
    """
    steps = rewards.shape[0]
    adv = torch.zeros_like(rewards)
    running = torch.zeros_like(last_value)
    for t in reversed(range(steps)):
        next_value = last_value if t == steps - 1 else values[t + 1]
        live = 1.0 - terminated[t].to(rewards.dtype)
        delta = rewards[t] + gamma * live * next_value - values[t]
        running = delta + gamma * lam * live * running
        adv[t] = running
    return adv, adv + values


def happo_surrogate(ratio: torch.Tensor, factor: torch.Tensor, advantage: torch.Tensor, clip_eps: float,
                    live: torch.Tensor) -> torch.Tensor:
    """HAPPO's clipped objective of one agent (to maximize): the mean over ``live`` samples of
    min(r M A, clip(r, 1 - eps, 1 + eps) M A), with r = ``ratio``, M = ``factor``, A = ``advantage`` (all (N,))."""
    weighted = factor * advantage
    surr = torch.minimum(ratio * weighted, torch.clamp(ratio, 1.0 - clip_eps, 1.0 + clip_eps) * weighted)
    live = live.to(surr.dtype)
    return (surr * live).sum() / live.sum().clamp(min=1.0)


class ValueNorm:
    """Running mean and variance of every return seen (Chan et al.'s parallel update), in float64."""

    def __init__(self):
        self.count, self.mean, self.var = 0.0, 0.0, 1.0

    def update(self, x: torch.Tensor) -> None:
        x = x.detach().double().flatten()
        n, m, v = float(x.numel()), float(x.mean()), float(x.var(unbiased=False))
        total = self.count + n
        delta = m - self.mean
        self.var = (self.count * self.var + n * v + delta ** 2 * self.count * n / total) / total
        self.mean += delta * n / total
        self.count = total

    def normalize(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.mean) / (self.var + 1e-8) ** 0.5

    def denormalize(self, x: torch.Tensor) -> torch.Tensor:
        return x * (self.var + 1e-8) ** 0.5 + self.mean

    def state_dict(self) -> dict:
        return {"count": self.count, "mean": self.mean, "var": self.var}

    def load_state_dict(self, state: dict) -> None:
        self.count, self.mean, self.var = float(state["count"]), float(state["mean"]), float(state["var"])


class Learner:
    """The shared graph-attention policy, the centralized critic, their optimizers and the value normalizer.

    Args:
        settings: GA-MATR's settings; n_agents: K; uav_in, context_in: token input widths; obs_dim: the flat
            observation's width; device: torch device.
    """

    def __init__(self, *, settings: GAMATRSettings, n_agents: int, uav_in: int, context_in: int, obs_dim: int,
                 device: str = "cpu"):
        s = settings
        self.settings, self.n_agents, self.device = s, n_agents, torch.device(device)
        self.policy = GraphAttentionPolicy(n_agents=n_agents, uav_in=uav_in, context_in=context_in,
                                           d_model=s.d_model, heads=s.heads, layers=s.layers,
                                           ffn_hidden=s.ffn_hidden, init_std=s.init_std,
                                           matmul_dtype=s.matmul_dtype).to(self.device)
        self.critic = CentralCritic(obs_dim=obs_dim, hidden=s.critic_hidden, depth=s.critic_depth).to(self.device)
        self.policy_opt = torch.optim.Adam(self.policy.parameters(), lr=s.actor_lr)
        self.critic_opt = torch.optim.Adam(self.critic.parameters(), lr=s.critic_lr)
        self.value_norm = ValueNorm()
        self.steps = 0

    # ---- acting ------------------------------------------------------------------------------------------
    @torch.no_grad()
    def value(self, critic_obs: torch.Tensor) -> torch.Tensor:
        """(N,) V(s) in raw units."""
        return self.value_norm.denormalize(self.critic(critic_obs))

    @torch.no_grad()
    def sample(self, x: PolicyInputs, gen: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        """Unclipped Gaussian actions (N, K, 3) drawn with ``gen`` and their log-probabilities (N, K)."""
        mean, std, _ = self.policy(x)
        noise = torch.randn(mean.shape, generator=gen).to(mean.device)
        action = mean + std * noise
        return action, log_prob(mean, std, action)

    # ---- update ------------------------------------------------------------------------------------------
    @torch.no_grad()
    def _agent_logp(self, x: PolicyInputs, action: torch.Tensor, chunk: int = 4096) -> torch.Tensor:
        """(N, K) log-probabilities of ``action`` under the current policy, in chunks of observations."""
        out = []
        for i in range(0, action.shape[0], chunk):
            part = PolicyInputs(*(t[i:i + chunk] for t in x))
            mean, std, _ = self.policy(part)
            out.append(log_prob(mean, std, action[i:i + chunk]))
        return torch.cat(out)

    def _step(self, opt: torch.optim.Optimizer, params, loss: torch.Tensor) -> None:
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, self.settings.max_grad_norm)
        opt.step()
        self.steps += 1

    def update(self, batch: Rollout, gen: torch.Generator, trace: list | None = None) -> dict[str, float]:
        """One HAPPO update on a rollout: every agent in turn (a permutation drawn from ``gen``), then the critic.

        Args:
            batch: the rollout; gen: draws the agents' order and the minibatches.
            trace: when a list, one dict per agent in update order is appended: {"agent", "factor" (N,) the
                weight of its surrogate, "ratio" (N,) its ratio right after its update, "policy" a copy of the
                policy's state right after its update}.

        Returns:
            {"policy": mean of minus the agents' surrogates, "value": mean critic loss, "entropy": mean entropy of
             the agents' Gaussians, "approx_kl": mean over agents of E[old logp - new logp] and "clip_fraction":
             mean over agents of the share of samples with |r - 1| > eps, both over the agent's live samples right
             after its update, "factor_std": std of the final factor M, "embedding_std": cross-agent std of the
             embeddings in the minibatches, "order": the agents' order}.
        """
        s, n = self.settings, batch.action.shape[0]
        adv = batch.advantage
        adv = (adv - adv.mean()) / (adv.std(unbiased=False) + 1e-8)
        available = batch.inputs.available
        order = torch.randperm(self.n_agents, generator=gen)
        factor = torch.ones(n, device=adv.device)
        policy_losses, kls, clipped, spreads = [], [], [], []
        for m in order.tolist():
            for _ in range(s.epochs):
                for idx in torch.randperm(n, generator=gen).to(adv.device).chunk(s.minibatches):
                    part = PolicyInputs(*(t[idx] for t in batch.inputs))
                    mean, std, emb = self.policy(part)
                    logp = log_prob(mean[:, m], std[m], batch.action[idx, m])
                    ratio = torch.exp(logp - batch.old_logp[idx, m])
                    live = available[idx, m]
                    surr = happo_surrogate(ratio, factor[idx], adv[idx], s.clip_eps, live)
                    loss = -surr - s.entropy_coef * entropy(std)[m]
                    self._step(self.policy_opt, self.policy.parameters(), loss)
                    policy_losses.append(-surr.item())
                    spreads.append(agent_embedding_std(emb.detach()).item())
            new_logp = self._agent_logp(batch.inputs, batch.action)[:, m]
            diff = new_logp - batch.old_logp[:, m]
            ratio = torch.where(available[:, m], torch.exp(diff), torch.ones_like(diff))
            live = available[:, m].float()
            kls.append(float((-diff * live).sum() / live.sum().clamp(min=1.0)))
            clipped.append(float((((ratio - 1).abs() > s.clip_eps).float() * live).sum() / live.sum().clamp(min=1.0)))
            if trace is not None:
                trace.append({"agent": m, "factor": factor.clone(), "ratio": ratio.clone(),
                              "policy": {k: v.detach().clone() for k, v in self.policy.state_dict().items()}})
            factor = factor * ratio
        # Critic on the returns in normalized units
        self.value_norm.update(batch.returns)
        target = self.value_norm.normalize(batch.returns).float()
        value_losses = []
        for _ in range(s.critic_epochs):
            for idx in torch.randperm(n, generator=gen).to(adv.device).chunk(s.minibatches):
                loss = torch.mean((self.critic(batch.critic_obs[idx]) - target[idx]) ** 2)
                self._step(self.critic_opt, self.critic.parameters(), loss)
                value_losses.append(loss.item())
        with torch.no_grad():
            ent = float(entropy(self.policy.log_std.exp()).mean())
        return {"policy": sum(policy_losses) / len(policy_losses), "value": sum(value_losses) / len(value_losses),
                "entropy": ent, "approx_kl": sum(kls) / len(kls), "clip_fraction": sum(clipped) / len(clipped),
                "factor_std": float(factor.std(unbiased=False)), "embedding_std": sum(spreads) / len(spreads),
                "order": order.tolist()}

    # ---- state -------------------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        """Weights, optimizer states, value normalizer and the gradient-step count."""
        return {"policy": self.policy.state_dict(), "critic": self.critic.state_dict(),
                "policy_opt": self.policy_opt.state_dict(), "critic_opt": self.critic_opt.state_dict(),
                "value_norm": self.value_norm.state_dict(), "steps": self.steps}

    def load_state_dict(self, state: dict) -> None:
        for name in ("policy", "critic", "policy_opt", "critic_opt", "value_norm"):
            getattr(self, name).load_state_dict(state[name])
        self.steps = int(state["steps"])
