"""Observation-anchored CEM decision-time planning (paper Algorithm 1, eqs. 17-18).

Two parts:
- ``cem``: a generic cross-entropy-method core over action sequences (N, H, *A) in [-1, 1].
- ``ImaginationScorer``: J(a_{t:t+H-1}) = sum_tau gamma^(tau-t) (SR_hat_tau - lambda_u u_tau) for a batch of N
  candidates in one tensor pass per imagined step: RSSM prior rollout, demand ensemble anchored on the
  observed map (rho), fleet positions and batteries propagated by ``dswm.fleet.fleet_step`` (the environment's
  own kinematics and battery rules), served ratio by the world model's service head (``dswm.physics``).
  With ``demand_override`` the true future maps replace the model's (no anchoring, no uncertainty), so the
  score is exactly the discounted SR the environment would realize.
``AnchoredCEMPlanner`` keeps the warm start (previous slot's mean, shifted by one step) between slots.
"""
from __future__ import annotations

import dataclasses
from typing import Callable, NamedTuple

import torch

from dswm.config import Scenario
from dswm.fleet import FleetState, Geometry, available, fleet_step
from dswm.physics import ServiceParams, served_ratio
from dswm.rssm import LatentState, map_state


@dataclasses.dataclass(frozen=True, kw_only=True)
class PlannerConfig:
    """CEM and scoring settings (values and reasons in config.yaml ``dswm.planner``)."""

    horizon: int
    """H, imagined slots."""
    n_samples: int
    """N_cem, candidate sequences per iteration."""
    n_elites: int
    """N_elite, sequences that refit the sampling distribution."""
    iterations: int
    """I, CEM iterations per slot."""
    sigma0: float
    """Initial sampling std of every action coordinate."""
    min_std: float
    """Floor of the refitted std (keeps exploring within a slot)."""
    gamma: float
    """Planner discount."""
    rho: float
    """Anchor mixing coefficient (eq. 18)."""
    lambda_u: float
    """Uncertainty penalty weight (0 for dswm_wo_unc)."""
    warm_start: bool
    """Start from the previous slot's mean shifted by one step (else from 0 = hold, proportional split)."""


class CEMResult(NamedTuple):
    best: torch.Tensor        # (H, *A) best-scoring sequence seen
    best_score: float
    mean: torch.Tensor        # (H, *A) final sampling mean
    std: torch.Tensor         # (H, *A) final sampling std
    scores: list[float]       # best score after each iteration


def cem(score_fn: Callable[[torch.Tensor], torch.Tensor], *, mean: torch.Tensor, std: torch.Tensor,
        n_samples: int, n_elites: int, iterations: int, min_std: float, generator: torch.Generator,
        seeds: torch.Tensor | None = None) -> CEMResult:
    """Maximize ``score_fn`` over sequences in [-1, 1] with the cross-entropy method.

    Args:
        score_fn: (N, H, *A) -> (N,) scores, higher is better.
        mean, std: (H, *A) initial diagonal Gaussian.
        n_samples, n_elites, iterations, min_std: CEM settings.
        generator: random source (same seed, same plan).
        seeds: optional (M, H, *A) sequences put into the first iteration's population (M < n_samples).
    Returns:
        CEMResult; the best sequence over all iterations (the best so far is re-entered in every iteration).
    """
    best, best_score, trace = None, -float("inf"), []
    for it in range(iterations):
        # Sample actions
        noise = torch.randn((n_samples, *mean.shape), generator=generator, device=mean.device, dtype=mean.dtype)
        cand = (mean + std * noise).clamp(-1.0, 1.0)
        fixed = [] if best is None else [best.unsqueeze(0)]
        if it == 0 and seeds is not None:
            fixed.append(seeds.to(cand).clamp(-1.0, 1.0))
        if fixed:
            fixed_t = torch.cat(fixed)[: n_samples - 1]
            cand[: fixed_t.shape[0]] = fixed_t
        # Score candidates
        scores = score_fn(cand)
        # Compute elite actions
        top = torch.topk(scores, n_elites).indices
        elites = cand[top]
        if float(scores[top[0]]) > best_score:
            best, best_score = cand[top[0]].clone(), float(scores[top[0]])
        trace.append(best_score)
        # Update parameters
        mean = elites.mean(0)
        std = elites.std(0, unbiased=False).clamp_min(min_std)
    return CEMResult(best, best_score, mean, std, trace)


def anchor(x_now: torch.Tensor, members: torch.Tensor, rho: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Persist anchoring (eq. 18) of every ensemble member and the uncertainty (eq. 17).

    Args:
        x_now: (G,) observed map x_t; members: (N, E, G) predicted maps of the E heads; rho: mixing weight.
    Returns:
        (x_hat (N, G): mean over heads of rho x_t + (1 - rho) x_e,
         u (N,): sum over cells of the heads' std of the anchored map / sum over cells of x_hat,
         i.e. the disagreement relative to the demand that is scored, dimensionless like SR).
    """
    # The anchored heads differ from their mean by (1 - rho) (x_e - mean_e x_e); written this way because a
    # reduction over the middle axis of (N, E, G) (torch.std(dim=1)) is an order of magnitude slower on CPU.
    m = members.mean(1)                                          # (N, G)
    x_hat = rho * x_now + (1.0 - rho) * m                        # (N, G)
    var = (members - m.unsqueeze(1)).square().mean(1)            # (N, G) population variance over heads
    spread = (1.0 - rho) * var.sqrt().sum(-1)                    # (N,)
    return x_hat, spread / x_hat.sum(-1).clamp_min(1e-8)


class ImaginationScorer:
    """Scores N candidate sequences (N, H, K, 3) from one decision point (see module docstring)."""

    def __init__(self, *, model, latent: LatentState | None, fleet: FleetState, x_now: torch.Tensor,
                 geom: Geometry, scenario: Scenario, params: ServiceParams, cells: torch.Tensor, gamma: float,
                 rho: float, lambda_u: float, demand_override: torch.Tensor | None = None):
        """Args:
            model: a ``WorldModel`` (may be None only with ``demand_override``).
            latent: posterior state at t, fields (1, .); fleet: FleetState at t with fields (K, ...).
            x_now: (G,) observed map x_t; cells: (G, 2); demand_override: (H, G) true maps x_{t+1..t+H}.
        """
        if model is None and demand_override is None:
            raise ValueError("ImaginationScorer: a world model is needed unless demand_override is given")
        self.model, self.latent, self.fleet, self.x_now = model, latent, fleet, x_now
        self.geom, self.scenario, self.params, self.cells = geom, scenario, params, cells
        self.gamma, self.rho, self.lambda_u, self.override = gamma, rho, lambda_u, demand_override

    @torch.no_grad()
    def __call__(self, actions: torch.Tensor) -> torch.Tensor:
        """Args: actions (N, H, K, 3) in [-1, 1].  Returns: J (N,)."""
        n, horizon = actions.shape[:2]
        fleet = self.fleet.expand(n)                                             # fields (N, K, ...)
        state = None if self.latent is None else map_state(self.latent, lambda x: x.expand(n, -1))
        score = torch.zeros(n, dtype=actions.dtype, device=actions.device)
        for tau in range(horizon):
            act = actions[:, tau]                                                # (N, K, 3)
            fleet, _ = fleet_step(fleet, act, self.geom, self.scenario)
            avail = available(fleet)                                             # (N, K)
            if self.override is not None:
                sr = served_ratio(self.override[tau], fleet.pos, avail, self.cells, params=self.params,
                                  bw_logit=act[..., 2])
                score += self.gamma ** (tau + 1) * sr
                continue
            rssm = self.model.rssm
            state = rssm.img_step(state, act.flatten(1), sample=False)
            feat = rssm.feat(state)                                              # (N, F)
            x_hat, u = anchor(self.x_now, self.model.demand_members(feat), self.rho)
            sr = self.model.service_sr(feat, x_hat, fleet.pos, avail, act[..., 2])
            score += self.gamma ** (tau + 1) * (sr - self.lambda_u * u)
        return score


class AnchoredCEMPlanner:
    """Per-slot CEM with warm start; holds the sampling mean between slots of one day."""

    def __init__(self, *, cfg: PlannerConfig, n_uavs: int, device: torch.device | str, seed: int):
        self.cfg, self.n_uavs, self.device = cfg, n_uavs, torch.device(device)
        self.generator = torch.Generator(device=self.device)
        self.seed = seed
        self.reset(0)

    def reset(self, day_seed: int) -> None:
        """Forget the warm start; reseed from (planner seed, day) so every day is reproducible alone."""
        self.generator.manual_seed(int(self.seed) * 1_000_003 + int(day_seed))
        self.prev_mean: torch.Tensor | None = None
        self.prev_best: torch.Tensor | None = None

    def _shift(self, seq: torch.Tensor) -> torch.Tensor:
        return torch.cat([seq[1:], torch.zeros_like(seq[:1])])

    def plan(self, score_fn: Callable[[torch.Tensor], torch.Tensor],
             proposals: torch.Tensor | None = None) -> tuple[torch.Tensor, CEMResult]:
        """Plan one slot.

        Args:
            score_fn: (N, H, K, 3) -> (N,), e.g. an ``ImaginationScorer``.
            proposals: optional (M, H, K, 3) extra seed sequences for the first iteration.
        Returns:
            (first action of the best sequence (K, 3), the CEMResult).
        """
        cfg = self.cfg
        shape = (cfg.horizon, self.n_uavs, 3)
        mean = torch.zeros(shape, device=self.device)
        seeds = [] if proposals is None else [proposals]
        if cfg.warm_start and self.prev_mean is not None:
            mean = self._shift(self.prev_mean)
            seeds.append(self._shift(self.prev_best).unsqueeze(0))
        std = torch.full(shape, cfg.sigma0, device=self.device)
        res = cem(score_fn, mean=mean, std=std, n_samples=cfg.n_samples, n_elites=cfg.n_elites,
                  iterations=cfg.iterations, min_std=cfg.min_std, generator=self.generator,
                  seeds=torch.cat(seeds) if seeds else None)
        self.prev_mean, self.prev_best = res.mean, res.best
        return res.best[0], res
