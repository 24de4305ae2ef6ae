"""Observation-anchored CEM decision-time planning (paper Algorithm 1, eqs. 17-18).

Two parts:
- ``cem``: a generic cross-entropy-method core over action sequences (N, H, *A) in [-1, 1].
- ``ImaginationScorer``: J(a_{t:t+H-1}) = sum_tau gamma^(tau-t) (SR_hat_tau - lambda_u u_tau) for a batch of N
  candidates in one tensor pass per imagined step: RSSM prior rollout, demand ensemble anchored on the
  observed map (rho), fleet positions and batteries propagated by ``dswm.sim.fleet.fleet_step`` (the environment's
  own kinematics and battery rules), served ratio by the world model's service head (``dswm.sim.physics``).
  With ``demand_override`` given maps replace the model's (no anchoring, no uncertainty): the true future maps
  (the perfect-forecast planner) or the current map held constant (the persistence probe).
``AnchoredCEMPlanner`` runs one slot's CEM and keeps what the next slot starts from.

With ``warm_start: false``, ``carry_best: false``, ``continuation: hold``, ``proposal: none`` and
``sigma0_later: null`` (config.yaml ``dswm.planner``, the method ``dswm``) this is Algorithm 1 as written: every
slot starts from mean 0 and std sigma0, every iteration samples its whole population from the refitted Gaussian,
imagined steps take the sampled actions, and the first action of the best sequence sampled is executed.
The project's planner, DSWM+ (config.yaml ``dswm.methods.dswm_plus``), adds choices beyond Algorithm 1, each with evidence from
training days in config.yaml:
- the first step and the later steps have their own initial std (``sigma0``, ``sigma0_later``), so the noise of
  the continuation does not decide which executed action wins;
- ``warm_start``/``carry_best``: the previous slot's mean, shifted, is the sampling mean, and the best sequences
  (the previous slot's and the best so far) re-enter the population;
- ``continuation="lloyd"``: later imagined steps add their sampled move to a Lloyd step, so imagined UAVs keep
  repositioning (e.g. fly back to demand after charging) instead of freezing;
- the population can be seeded with proposals (``AnchoredCEMPlanner.plan(proposals=...)``); the controller
  passes the project's one BCD search (config.yaml ``search``) on the first imagined map
  (``dswm.methods.dswm.agent.BCDProposal``).
"""
from __future__ import annotations

import dataclasses
import functools
from typing import Callable, Literal, NamedTuple

import torch

from dswm.config import ENUM, GIVEN, ConfigError, check_fields, setting
from dswm.sim.scenario import Scenario
from dswm.methods.collect import lloyd_step
from dswm.methods.search import SearchSettings
from dswm.sim.fleet import FleetState, Geometry, available, fleet_step
from dswm.sim.physics import ServiceParams, service
from dswm.methods.dswm.rssm import LatentState, map_state

CONTINUATIONS = ("hold", "lloyd")


@dataclasses.dataclass(frozen=True, kw_only=True)
class PlannerConfig:
    """CEM and scoring settings (values and reasons in config.yaml ``dswm.planner``)."""

    horizon: int = setting("count")
    """H, imagined slots."""
    n_samples: int = setting("count")
    """N_cem, candidate sequences per iteration."""
    n_elites: int = setting("count")
    """N_elite, sequences that refit the sampling distribution."""
    iterations: int = setting("count")
    """I, CEM iterations per slot."""
    sigma0: float = setting("positive")
    """Initial sampling std of the first step's action coordinates (Algorithm 1: of every step)."""
    sigma0_later: float | None = setting(schema={
        "anyOf": [{"type": "number", "exclusiveMinimum": 0}, {"type": "null"}],
        "description": "a positive number, or null (the same as sigma0)"})
    """Initial sampling std of the later steps; None: ``sigma0`` (Algorithm 1)."""
    min_std: float = setting("nonnegative")
    """Floor of the refitted std (0: none, as in Algorithm 1)."""
    gamma: float = setting("fraction")
    """Planner discount."""
    rho: float = setting("fraction")
    """Anchor mixing coefficient (eq. 18)."""
    rho_steps: tuple[float, ...] | None = setting(schema={
        "anyOf": [{"type": "array", "minItems": 1, "items": {"type": "number", "minimum": 0, "maximum": 1}},
                  {"type": "null"}],
        "description": "a list of H numbers in [0, 1] (rho_k of imagined step k = 1..H), or null (rho at every step)"},
        default=None)
    """Anchoring per imagined step: rho_k of step k = 1..H in place of ``rho``; None: ``rho`` at every step (the
    methods of config.yaml; the room-fill candidate takes rho_k fitted on training days,
    ``dswm.pipeline.room_fill``)."""
    lambda_u: float = setting("nonnegative")
    """Uncertainty penalty weight (0 for dswm_wo_unc)."""
    warm_start: bool = setting("flag")
    """Start from the previous slot's mean shifted by one step (else from 0 = hold, proportional split)."""
    carry_best: bool = setting("flag")
    """Re-enter the best sequence so far into every iteration's population (and the previous slot's best, shifted,
    with ``warm_start``); off in Algorithm 1, where every iteration samples its whole population."""
    continuation: Literal["hold", "lloyd"] = setting(ENUM)
    """"hold" or "lloyd": how imagined steps after the first act (see ``ImaginationScorer``)."""
    proposal: Literal["none", "bcd"] = setting(ENUM)
    """"none" or "bcd": seed the population with the shared BCD ``search`` on the first imagined map."""
    search: SearchSettings = setting(GIVEN)
    """The project's one BCD search (config.yaml ``search``), run by the "bcd" proposal."""
    compile: bool = setting("flag")
    """Run the imagined steps compiled by ``torch.compile`` (``ImaginationScorer``)."""
    imagine_scale: float = setting("positive", default=1.0)
    """s of the do(s) probe: every imagined demand map the planner scores on (and the proposal searches on) is
    multiplied by s at decision time; 1 in every evaluated method. Never a training setting."""

    def __post_init__(self):
        check_fields(self, "dswm.planner")
        if self.rho_steps is not None:
            object.__setattr__(self, "rho_steps", tuple(float(r) for r in self.rho_steps))
            if len(self.rho_steps) != self.horizon:
                raise ConfigError(f"config key dswm.planner.rho_steps: expected {self.horizon} numbers (one per "
                                  f"imagined step, horizon {self.horizon}), found {len(self.rho_steps)}")

    def rho_at(self, step: int) -> float:
        """The anchoring of imagined step ``step`` (1..H): ``rho_steps[step - 1]``, or ``rho`` without them."""
        return self.rho if self.rho_steps is None else self.rho_steps[step - 1]

    @property
    def later_std(self) -> float:
        """Initial std of the steps after the first."""
        return self.sigma0 if self.sigma0_later is None else self.sigma0_later


class CEMResult(NamedTuple):
    best: torch.Tensor        # (H, *A) best-scoring sequence seen
    best_score: float
    mean: torch.Tensor        # (H, *A) final sampling mean
    std: torch.Tensor         # (H, *A) final sampling std
    scores: list[float]       # best score after each iteration


def cem(score_fn: Callable[[torch.Tensor], torch.Tensor], *, mean: torch.Tensor, std: torch.Tensor,
        n_samples: int, n_elites: int, iterations: int, min_std: float, generator: torch.Generator,
        seeds: torch.Tensor | None = None, carry_best: bool = True) -> CEMResult:
    """Maximize ``score_fn`` over sequences in [-1, 1] with the cross-entropy method.

    Args:
        score_fn: (N, H, *A) -> (N,) scores, higher is better.
        mean, std: (H, *A) initial diagonal Gaussian.
        n_samples, n_elites, iterations, min_std: CEM settings.
        generator: random source (same seed, same plan).
        seeds: optional (M, H, *A) sequences put into the first iteration's population (M < n_samples).
        carry_best: re-enter the best sequence so far into every later iteration's population.
    Returns:
        CEMResult; the best sequence over all iterations.
    """
    best, best_score, trace = None, -float("inf"), []
    for it in range(iterations):
        # Sample actions
        noise = torch.randn((n_samples, *mean.shape), generator=generator, device=mean.device, dtype=mean.dtype)
        cand = (mean + std * noise).clamp(-1.0, 1.0)
        fixed = [] if best is None or not carry_best else [best.unsqueeze(0)]
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
        x_now: (G,) observed map x_t; members: (E, N, G) predicted maps of the E heads; rho: mixing weight.
    Returns:
        (x_hat (N, G): mean over heads of rho x_t + (1 - rho) x_e,
         u (N,): sum over cells of the heads' std of the anchored map / sum over cells of x_hat,
         i.e. the disagreement relative to the demand that is scored, dimensionless like SR).
    """
    # The anchored heads differ from their mean by (1 - rho) (x_e - mean_e x_e).
    e = members.shape[0]
    m = members.sum(0) / e                                       # (N, G)
    x_hat = rho * x_now + (1.0 - rho) * m                        # (N, G)
    # Population variance over heads, one head at a time: broadcasting (E, N, G) against (N, G) and
    # reducing over the leading axis is several times slower on CPU.
    var = torch.zeros_like(m)
    for j in range(e):
        d = members[j] - m
        var.addcmul_(d, d)
    var /= e                                                     # (N, G)
    spread = (1.0 - rho) * var.sqrt().sum(-1)                    # (N,)
    return x_hat, spread / x_hat.sum(-1).clamp_min(1e-8)


@dataclasses.dataclass(frozen=True, kw_only=True)
class ImaginedWorld:
    """The place every imagined step plays in: fixed over a day (one grid, one scenario)."""

    cells: torch.Tensor
    """(G, 2) cell centres in metres."""
    geom: Geometry
    """The grid's geometry (bounds, charging stations) the fleet kinematics use."""
    scenario: Scenario
    """The fleet's scenario (UAV count, speeds, batteries)."""
    params: ServiceParams
    """The service physics' parameters."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class StepScoring:
    """How an imagined step turns its demand into the planner's reward (config.yaml ``dswm.planner``)."""

    rho: float
    """Anchor mixing coefficient (eq. 18)."""
    lambda_u: float
    """Uncertainty penalty weight (0: the served ratio alone)."""
    continuation: str
    """"hold" or "lloyd": how imagined steps after the first act (see ``ImaginationScorer``)."""
    scale: float = 1.0
    """s of the do(s) probe, the factor of the imagined demand (the anchored map, or the given map); the
    uncertainty u, relative to the scored demand, does not change with it."""
    rho_steps: tuple[float, ...] | None = None
    """rho_k of imagined step k = 1..H in place of ``rho`` (``planner.rho_steps``); None: ``rho`` at every step."""

    def at(self, tau: int) -> "StepScoring":
        """The scoring of imagined step ``tau + 1``: this one, with rho = rho_{tau+1} when ``rho_steps`` is given."""
        if self.rho_steps is None:
            return self
        return dataclasses.replace(self, rho=float(self.rho_steps[tau]), rho_steps=None)


def imagined_step(model, fleet: FleetState, state: LatentState | None, act: torch.Tensor,
                  x_prev: torch.Tensor | None, assoc: torch.Tensor | None, *, x_now: torch.Tensor,
                  x_true: torch.Tensor | None, world: ImaginedWorld, scoring: StepScoring, first: bool):
    """One imagined slot of N candidates (the body of ``ImaginationScorer``; see there).

    Args:
        model: the world model (unused with ``x_true``); fleet: FleetState with fields (N, K, ...);
        state: RSSM state (N, .) or None with ``x_true``; act: (N, K, 3) sampled action of this step;
        x_prev, assoc: (N, G) demand and association of the previous imagined slot (None when ``first``);
        x_now: (G,) observed map; x_true: (G,) true map of this slot, or None for the model's anchored map;
        world: grid, geometry, scenario and service physics; scoring: rho, lambda_u, continuation and the
            do(s) factor ``scale``;
        first: the step that executes the first action (no continuation).
    Returns:
        (fleet, state, action taken (N, K, 3), demand (N, G), association (N, G), reward SR - lambda_u u (N,)).
    """
    cells, geom, scenario, params = world.cells, world.geom, world.scenario, world.params
    rho, lambda_u, continuation, scale = scoring.rho, scoring.lambda_u, scoring.continuation, scoring.scale
    # Continuation: later steps ride on a Lloyd step of the previous imagined slot.
    if not first and continuation == "lloyd":
        base = lloyd_step(x_prev, assoc, fleet.pos, cells, scenario.d_max_m)
        act = torch.cat([(act[..., :2] + base).clamp(-1.0, 1.0), act[..., 2:]], -1)
    # Fleet kinematics and batteries: the environment's own rules.
    fleet, _ = fleet_step(fleet, act, geom, scenario)
    avail = available(fleet)                                                     # (N, K)
    if x_true is not None:
        if scale != 1.0:
            x_true = scale * x_true
        res = service(x_true, fleet.pos, avail, cells, params=params, bw_logit=act[..., 2])
        return fleet, state, act, x_true, res.assoc, res.sr
    # Prior rollout, anchored demand ensemble, service head.
    rssm = model.rssm
    state = rssm.img_step(state, act.flatten(1), sample=False)
    feat = rssm.feat(state)                                                      # (N, F)
    x_hat, u = anchor(x_now, model.demand_members(feat), rho)
    if scale != 1.0:
        x_hat = scale * x_hat
    sr, assoc = model.serve(feat, x_hat, fleet.pos, avail, act[..., 2], need_assoc=continuation == "lloyd")
    return fleet, state, act, x_hat, assoc, sr - lambda_u * u


@functools.cache
def _compiled_step():
    """``imagined_step`` compiled by ``torch.compile`` (one whole graph per shape and step kind, built on first use)."""
    return torch.compile(imagined_step, dynamic=False, fullgraph=True)


class ImaginationScorer:
    """Scores N candidate sequences (N, H, K, 3) from one decision point (see module docstring).

    ``continuation`` says how the steps after the executed first action act on the imagined fleet:
    "hold" takes the sampled sequence as it is (open loop); "lloyd" adds the sampled (dx, dy) of every later
    step to a Lloyd step toward the centroid of each UAV's served demand, so that imagined UAVs keep
    repositioning (e.g. fly back to demand after charging) instead of freezing where the sequence left them.
    With ``compile`` each imagined step runs as code compiled by ``torch.compile``: the same functions, fused
    into a few loops (the first call in a process compiles, seconds). ``scoring.scale`` (s of the do(s) probe,
    ``planner.imagine_scale``) multiplies every imagined demand map before it is scored.
    """

    def __init__(self, *, model, latent: LatentState | None, fleet: FleetState, x_now: torch.Tensor,
                 world: ImaginedWorld, scoring: StepScoring, gamma: float, compile: bool,
                 demand_override: torch.Tensor | None = None):
        """Args:
            model: a ``WorldModel`` (may be None only with ``demand_override``).
            latent: posterior state at t, fields (1, .); fleet: FleetState at t with fields (K, ...).
            x_now: (G,) observed map x_t; world: grid cells (G, 2), geometry, scenario and service physics;
            scoring: rho, lambda_u, continuation ("hold" or "lloyd") and ``scale``, the factor s > 0 of the
                imagined demand (``planner.imagine_scale``; 1: as imagined); gamma: planner discount;
            demand_override: (H, G) true maps x_{t+1..t+H} (then no anchoring and no uncertainty);
            compile: run the imagined steps compiled (``planner.compile``).
        """
        if model is None and demand_override is None:
            raise ValueError("ImaginationScorer: a world model is needed unless demand_override is given")
        if scoring.continuation not in CONTINUATIONS:
            raise ValueError(f"ImaginationScorer: continuation must be one of {CONTINUATIONS}, "
                             f"found {scoring.continuation!r}")
        if not scoring.scale > 0:
            raise ValueError(f"ImaginationScorer: imagine_scale must be a positive number, found {scoring.scale!r}")
        self.model, self.latent, self.fleet, self.x_now = model, latent, fleet, x_now
        self.world, self.gamma, self.override = world, gamma, demand_override
        self.scoring = dataclasses.replace(scoring, scale=float(scoring.scale))
        self.step = _compiled_step() if compile else imagined_step
        self.last_actions: torch.Tensor | None = None

    @torch.no_grad()
    def __call__(self, actions: torch.Tensor) -> torch.Tensor:
        """Args: actions (N, H, K, 3) in [-1, 1].  Returns: J (N,); ``last_actions`` holds the actions the
        imagined fleet actually took (N, H, K, 3), i.e. with the continuation applied."""
        n, horizon = actions.shape[:2]
        fleet = self.fleet.expand(n)                                             # fields (N, K, ...)
        state = None if self.latent is None else map_state(self.latent, lambda x: x.expand(n, -1))
        score = torch.zeros(n, dtype=actions.dtype, device=actions.device)
        taken, x_prev, assoc = [], None, None
        for tau in range(horizon):
            fleet, state, act, x_prev, assoc, reward = self.step(
                self.model, fleet, state, actions[:, tau], x_prev, assoc, x_now=self.x_now,
                x_true=None if self.override is None else self.override[tau], world=self.world,
                scoring=self.scoring.at(tau), first=tau == 0)
            taken.append(act)
            score += self.gamma ** (tau + 1) * reward
        self.last_actions = torch.stack(taken, 1)
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

    def warm_mean(self) -> torch.Tensor:
        """(H, K, 3) the sampling mean this slot starts from: the previous mean shifted, or 0."""
        if self.cfg.warm_start and self.prev_mean is not None:
            return self._shift(self.prev_mean)
        return torch.zeros((self.cfg.horizon, self.n_uavs, 3), device=self.device)

    def warm_best(self) -> torch.Tensor | None:
        """(H, K, 3) the previous slot's best sequence shifted by one step (with ``warm_start`` and
        ``carry_best``), or None."""
        if self.cfg.warm_start and self.cfg.carry_best and self.prev_best is not None:
            return self._shift(self.prev_best)
        return None

    def plan(self, score_fn: Callable[[torch.Tensor], torch.Tensor],
             proposals: torch.Tensor | None = None) -> tuple[torch.Tensor, CEMResult]:
        """Plan one slot.

        Args:
            score_fn: (N, H, K, 3) -> (N,), e.g. an ``ImaginationScorer``.
            proposals: optional (M, H, K, 3) seed sequences for the first iteration; the sampling mean's first
                step is set to the first proposal's first action.
        Returns:
            (first action of the best sequence (K, 3), the CEMResult).
        """
        cfg = self.cfg
        shape = (cfg.horizon, self.n_uavs, 3)
        mean = self.warm_mean().clone()
        seeds = []
        if proposals is not None:
            mean[0] = proposals[0, 0]
            seeds.append(proposals)
        if self.warm_best() is not None:
            seeds.append(self.warm_best().unsqueeze(0))
        std = torch.full(shape, cfg.later_std, device=self.device)
        std[0] = cfg.sigma0
        res = cem(score_fn, mean=mean, std=std, n_samples=cfg.n_samples, n_elites=cfg.n_elites,
                  iterations=cfg.iterations, min_std=cfg.min_std, generator=self.generator,
                  seeds=torch.cat(seeds) if seeds else None, carry_best=cfg.carry_best)
        self.prev_mean, self.prev_best = res.mean, res.best
        return res.best[0], res
