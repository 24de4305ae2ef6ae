"""TD-MPC's decision-time planner: MPPI over H-slot action sequences in the TOLD's latent space.

Per slot, for B observations at once, from their latents z:
1. policy sequences: ``n_policy`` rollouts of pi (with ``min_std`` noise) through the latent dynamics;
2. a diagonal Gaussian over (H, A) sequences, its mean the previous slot's final mean shifted by one step
   (warm start; zero at the day's first slot and in the last step), its std ``max_std``;
3. ``iterations`` times: sample ``n_samples`` sequences (clipped to [-1, 1]) beside the policy's, score each by
   G = sum_t gamma^t R(z_t, a_t) + gamma^H min_i Q_i(z_H, pi(z_H)) (the TD-learned value closes the horizon),
   keep the ``n_elites`` best, weight them by exp(temperature (G - max G)) and refit mean (with ``momentum``)
   and std (clamped to [min_std, max_std]) to them;
4. as in TD-MPC, one elite sequence is drawn by its weight and its first action is executed (with the final
   first-step std as exploration noise while collecting), clipped to [-1, 1].

With ``matmul_dtype`` bfloat16 (the setting of TD-MPC's gradient step) the latent rollouts run under torch's autocast:
the networks' matrix products in bfloat16 with float32 accumulation, the latents between steps in bfloat16; every
predicted reward and value is taken back to float32 before it is summed, and the sampling, the elites' weights and
the refit stay float32. ``float32`` computes every operation as before the setting reached planning, bit for bit.
"""
from __future__ import annotations

import dataclasses
from typing import NamedTuple

import torch

from dswm.methods.matmul import MatmulDtype, autocast


@dataclasses.dataclass(frozen=True, kw_only=True)
class MPPIConfig:
    """MPPI's settings (``TDMPCSettings.mppi``)."""

    horizon: int
    n_samples: int
    n_policy: int
    """Policy sequences added to the Gaussian's samples."""
    n_elites: int
    iterations: int
    temperature: float
    momentum: float
    min_std: float
    max_std: float
    gamma: float
    matmul_dtype: MatmulDtype = "float32"
    """The latent rollouts' products (:mod:`dswm.methods.matmul`'s names; see the module docstring)."""


class MPPIResult(NamedTuple):
    action: torch.Tensor   # (B, A) first action to execute, in [-1, 1]
    mean: torch.Tensor     # (B, H, A) final sampling mean (the next slot's warm start, shifted)
    std: torch.Tensor      # (B, H, A) final sampling std
    value: torch.Tensor    # (B,) weighted mean of the elites' returns G


@torch.no_grad()
def sequence_returns(model, z: torch.Tensor, actions: torch.Tensor, gamma: float) -> torch.Tensor:
    """G of each sequence: sum_t gamma^t R(z_t, a_t) + gamma^H min_i Q_i(z_H, pi(z_H)).

    Args:
        model: has ``next(z, a) -> (z', r)``, ``q(z, a) -> (q1, q2)`` and ``pi(z)`` (a ``TOLD``);
        z: (..., latent) start latents; actions: (H, ..., A).
    Returns:
        (...) returns.
    """
    g, disc = 0.0, 1.0
    for a in actions:
        z, r = model.next(z, a)
        g = g + disc * r.float()
        disc *= gamma
    q1, q2 = model.q(z, model.pi(z))
    return g + disc * torch.minimum(q1, q2).float()


@torch.no_grad()
def policy_sequences(model, z: torch.Tensor, *, n: int, horizon: int, std: float,
                     generator: torch.Generator | None) -> torch.Tensor:
    """(H, B, n, A) rollouts of pi with ``std`` noise through the latent dynamics from z (B, latent)."""
    zp = z.unsqueeze(1).expand(z.shape[0], n, z.shape[-1])
    out = []
    for _ in range(horizon):
        a = model.pi(zp, std, generator)
        out.append(a.float())
        zp, _ = model.next(zp, a)
    return torch.stack(out)


@torch.no_grad()
def mppi(model, z: torch.Tensor, *, cfg: MPPIConfig, generator: torch.Generator,
         prev_mean: torch.Tensor | None = None, explore: bool = False) -> MPPIResult:
    """Plan one slot for B latents z (B, latent); see the module docstring.

    Args:
        model: a ``TOLD`` (or any object with its ``next``, ``q``, ``pi`` and ``action_dim``);
        cfg: settings; generator: random source (on z's device; same seed, same plan);
        prev_mean: (B, H, A) the previous slot's final mean, or None at a day's first slot;
        explore: add the final first-step std as Gaussian noise to the executed action (collection only).
    """
    with autocast(z.device.type, cfg.matmul_dtype):
        return _mppi(model, z, cfg=cfg, generator=generator, prev_mean=prev_mean, explore=explore)


def _mppi(model, z: torch.Tensor, *, cfg: MPPIConfig, generator: torch.Generator, prev_mean: torch.Tensor | None,
          explore: bool) -> MPPIResult:
    """:func:`mppi`'s body, under the autocast of ``cfg.matmul_dtype``."""
    b, h, n, e = z.shape[0], cfg.horizon, cfg.n_samples, cfg.n_elites
    a_dim = model.action_dim
    kw = {"device": z.device, "dtype": z.dtype}
    # Policy sequences
    pi_seq = (policy_sequences(model, z, n=cfg.n_policy, horizon=h, std=cfg.min_std, generator=generator)
              if cfg.n_policy > 0 else torch.zeros(h, b, 0, a_dim, **kw))
    # Initial distribution (warm start: the previous mean shifted by one step)
    mean = torch.zeros(h, b, a_dim, **kw)
    if prev_mean is not None:
        mean[:-1] = prev_mean.transpose(0, 1)[1:]
    std = torch.full((h, b, a_dim), cfg.max_std, **kw)
    z_all = z.unsqueeze(1).expand(b, n + cfg.n_policy, z.shape[-1])
    for _ in range(cfg.iterations):
        # Sample actions
        noise = torch.randn((h, b, n, a_dim), generator=generator, **kw)
        cand = torch.cat([(mean.unsqueeze(2) + std.unsqueeze(2) * noise).clamp(-1.0, 1.0), pi_seq], 2)
        # Compute elite actions
        returns = sequence_returns(model, z_all, cand, cfg.gamma)                    # (B, N + n_pi)
        value, idx = returns.topk(e, dim=1)                                          # (B, E)
        elite = cand.gather(2, idx.view(1, b, e, 1).expand(h, b, e, a_dim))          # (H, B, E, A)
        # Update parameters
        w = torch.exp(cfg.temperature * (value - value.max(1, keepdim=True).values))
        w = w / w.sum(1, keepdim=True)                                               # (B, E)
        wx = w.view(1, b, e, 1)
        fit = (wx * elite).sum(2)                                                    # (H, B, A)
        std = torch.sqrt((wx * (elite - fit.unsqueeze(2)) ** 2).sum(2)).clamp(cfg.min_std, cfg.max_std)
        mean = cfg.momentum * mean + (1.0 - cfg.momentum) * fit
    # Select the executed action: one elite drawn by weight, its first step
    pick = torch.multinomial(w, 1, generator=generator)                              # (B, 1)
    action = elite[0].gather(1, pick.view(b, 1, 1).expand(b, 1, a_dim)).squeeze(1)
    if explore:
        action = action + std[0] * torch.randn((b, a_dim), generator=generator, **kw)
    return MPPIResult(action=action.clamp(-1.0, 1.0), mean=mean.transpose(0, 1), std=std.transpose(0, 1),
                      value=(w * value).sum(1))
