"""Recurrent state-space model (paper eqs. 8-12): GRU deterministic path, diagonal-Gaussian stochastic state.

API in the DreamerV3-port style: ``obs_step`` (posterior), ``img_step`` (prior), ``observe`` (a sequence),
``kl_loss`` (0.8/0.2 balanced KL with a per-dimension free-bits floor). Shapes in comments use
B = batch (any leading axes flattened by the caller), T = time, D = deter, S = stoch, A = action, E = embed.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import nn
from torch.nn import functional as F

from dswm.config import check_fields, setting


@dataclass(frozen=True, kw_only=True)
class RSSMConfig:
    """Sizes and KL settings of the RSSM (values and reasons in config.yaml ``dswm.world_model``)."""

    deter: int = setting("count")
    """Size of the GRU state h."""
    stoch: int = setting("count")
    """Size of the diagonal-Gaussian state z."""
    hidden: int = setting("count")
    """Width of the prior/posterior MLPs and of the GRU input layer."""
    embed: int = setting("count")
    """Size of the observation embedding e_psi(o_t)."""
    min_std: float = setting("positive")
    """Lower bound of the Gaussian std, keeps the KL finite."""
    free_bits: float = setting("nonnegative")
    """Per-dimension KL floor in nats (eq. 12)."""
    kl_dyn: float = setting("nonnegative")
    """Weight of KL(sg[q] || p): trains the prior."""
    kl_rep: float = setting("nonnegative")
    """Weight of KL(q || sg[p]): trains the posterior."""

    def __post_init__(self):
        check_fields(self, "dswm.world_model")


class LatentState(NamedTuple):
    """One RSSM state; every field has leading axes (..., ) shared with the batch."""

    deter: torch.Tensor  # (..., D) h_t
    stoch: torch.Tensor  # (..., S) z_t (sample or mean)
    mean: torch.Tensor   # (..., S)
    std: torch.Tensor    # (..., S)


def stack_states(states: list[LatentState], dim: int = 0) -> LatentState:
    """Stack a list of states along a new axis ``dim``."""
    return LatentState(*(torch.stack(field, dim) for field in zip(*states)))


def map_state(state: LatentState, fn) -> LatentState:
    """Apply ``fn`` to every tensor of a state (reshape, index, detach...)."""
    return LatentState(*(fn(t) for t in state))


class RSSM(nn.Module):
    """h_t = f(h_{t-1}, z_{t-1}, a_{t-1});  p(z_t | h_t);  q(z_t | h_t, e(o_t))."""

    def __init__(self, *, cfg: RSSMConfig, action_dim: int):
        super().__init__()
        self.cfg = cfg
        self.inp = nn.Sequential(nn.Linear(cfg.stoch + action_dim, cfg.hidden), nn.ELU())
        self.gru = nn.GRUCell(cfg.hidden, cfg.deter)
        self.prior_net = nn.Sequential(nn.Linear(cfg.deter, cfg.hidden), nn.ELU(),
                                       nn.Linear(cfg.hidden, 2 * cfg.stoch))
        self.post_net = nn.Sequential(nn.Linear(cfg.deter + cfg.embed, cfg.hidden), nn.ELU(),
                                      nn.Linear(cfg.hidden, 2 * cfg.stoch))

    @property
    def feat_dim(self) -> int:
        return self.cfg.deter + self.cfg.stoch

    def initial(self, batch: int, device=None) -> LatentState:
        """All-zero state for ``batch`` sequences (start of a day or of a replayed window)."""
        zd = torch.zeros(batch, self.cfg.deter, device=device)
        zs = torch.zeros(batch, self.cfg.stoch, device=device)
        return LatentState(zd, zs, zs, torch.ones_like(zs))

    def _gaussian(self, stats: torch.Tensor, sample: bool) -> tuple[torch.Tensor, ...]:
        mean, raw = stats.chunk(2, dim=-1)
        std = F.softplus(raw) + self.cfg.min_std
        stoch = mean + std * torch.randn_like(std) if sample else mean
        return stoch, mean, std

    def img_step(self, prev: LatentState, prev_action: torch.Tensor, *, sample: bool = True) -> LatentState:
        """Prior step (imagination).

        Args:
            prev: state at t-1, fields (B, .).
            prev_action: a_{t-1} flattened, (B, A).
            sample: draw z_t from the prior (training) or take its mean (planning).
        Returns:
            prior state at t: deter (B, D), stoch/mean/std (B, S).
        """
        x = self.inp(torch.cat([prev.stoch, prev_action], -1))           # (B, hidden)
        deter = self.gru(x, prev.deter)                                    # (B, D)
        stoch, mean, std = self._gaussian(self.prior_net(deter), sample)   # (B, S) each
        return LatentState(deter, stoch, mean, std)

    def obs_step(self, prev: LatentState, prev_action: torch.Tensor, embed: torch.Tensor,
                 *, sample: bool = True) -> tuple[LatentState, LatentState]:
        """Posterior step (filtering an observation).

        Args:
            prev: state at t-1; prev_action: (B, A); embed: e_psi(o_t), (B, E).
        Returns:
            (posterior, prior) at t, both with deter (B, D) and stoch/mean/std (B, S); they share h_t.
        """
        prior = self.img_step(prev, prev_action, sample=sample)
        stats = self.post_net(torch.cat([prior.deter, embed], -1))
        stoch, mean, std = self._gaussian(stats, sample)
        return LatentState(prior.deter, stoch, mean, std), prior

    def observe(self, embeds: torch.Tensor, prev_actions: torch.Tensor, init: LatentState,
                *, sample: bool = True) -> tuple[LatentState, LatentState]:
        """Filter a sequence.

        Args:
            embeds: (T, B, E); prev_actions: (T, B, A), entry t is a_{t-1}; init: state before step 0, (B, .).
        Returns:
            (posteriors, priors) with fields (T, B, .).
        """
        posts, priors, state = [], [], init
        for t in range(embeds.shape[0]):
            state, prior = self.obs_step(state, prev_actions[t], embeds[t], sample=sample)
            posts.append(state)
            priors.append(prior)
        return stack_states(posts), stack_states(priors)

    @staticmethod
    def feat(state: LatentState) -> torch.Tensor:
        """Model feature [h, z], (..., D + S)."""
        return torch.cat([state.deter, state.stoch], -1)

    def kl_loss(self, post: LatentState, prior: LatentState) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """Balanced free-bits KL (eq. 12).

        ``kl_dyn * KL(sg[q] || p) + kl_rep * KL(q || sg[p])``; each per-dimension KL is clipped from below
        by ``free_bits`` before the sum over dimensions, then averaged over the leading axes.

        Args:
            post, prior: states with fields (..., S).
        Returns:
            (loss scalar, {"kl": unclipped KL(q||p) summed over dims, "kl_dyn", "kl_rep"}).
        """
        floor = self.cfg.free_bits
        dyn = gaussian_kl(post.mean.detach(), post.std.detach(), prior.mean, prior.std)  # trains the prior
        rep = gaussian_kl(post.mean, post.std, prior.mean.detach(), prior.std.detach())  # trains the posterior
        dyn_c = torch.clamp(dyn, min=floor).sum(-1).mean()
        rep_c = torch.clamp(rep, min=floor).sum(-1).mean()
        loss = self.cfg.kl_dyn * dyn_c + self.cfg.kl_rep * rep_c
        return loss, {"kl": dyn.detach().sum(-1).mean(), "kl_dyn": dyn_c.detach(), "kl_rep": rep_c.detach()}


def gaussian_kl(mean_q: torch.Tensor, std_q: torch.Tensor, mean_p: torch.Tensor,
                std_p: torch.Tensor) -> torch.Tensor:
    """Per-dimension KL(N(mean_q, std_q^2) || N(mean_p, std_p^2)), same shape as the inputs."""
    var_ratio = (std_q / std_p) ** 2
    return 0.5 * (var_ratio + ((mean_q - mean_p) / std_p) ** 2 - 1.0 - torch.log(var_ratio))
