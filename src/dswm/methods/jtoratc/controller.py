"""JTORATC's per-slot block-coordinate descent, the paper's degradation rule, and the controller.

Per decision (:func:`solve_slot`), on the current observed map x_t and the fleet after the slot, starting from
every UAV where it is, the environment's nearest association and its KKT bandwidth, rounds of
1. association (``model.association_block``: relaxed, improved, rounded), kept only if J falls with it;
2. bandwidth (``model.bandwidth_block``): the KKT split of the kept association at the current positions;
3. trajectory: up to ``sca_iters`` SCA steps (``sca.TrajectoryProgram``), association and bandwidth held; a step
   is kept only if the exact J falls (else the trust region halves); a solver failure keeps the last positions;
until a round lowers J by less than ``bcd_tol`` of it, or ``bcd_iters`` rounds. J never rises.

Execution: the environment associates every cell with its nearest UAV, whatever the BCD's association was; that
association shaped where the trajectory block moved each UAV (towards the cells it was given). The bandwidth
logit sent is the one whose x^tau split fits the KKT split of the environment's association at the planned
positions (``model.fit_bandwidth_logit``).

Degradation rule (paper Section V): the paper's solves took over 8 s per slot at K = 16, which forced one solve
per 6 slots with fewer SCA iterations. Here, once a solve takes longer than ``solve_budget_ms`` (wall time), the
rest of the day solves every ``degrade_every`` slots with ``degraded_sca_iters`` SCA steps and holds the plan in
between (flying on to the planned positions with the same logits). :meth:`JTORATCController.day_stats` counts it.
"""
from __future__ import annotations

import dataclasses
import logging
import time
from typing import TYPE_CHECKING, Any, ClassVar, Mapping, NamedTuple

import numpy as np
import torch

from dswm.config import ConfigError, check_fields, setting
from dswm.methods.base import Controller, DayContext
from dswm.methods.jtoratc.model import (Slot, association_block, bandwidth_block, concave_bridges,
                                        fit_bandwidth_logit, nearest, objective, rate_surrogate)
from dswm.methods.search import to_action
from dswm.sim.core import fleet_state_from_obs
from dswm.sim.fleet import ACTIVE, fleet_step
from dswm.sim.physics import DEMAND_EPS, ServiceParams

if TYPE_CHECKING:  # cvxpy is imported where a program is built: reading the settings needs none of it
    from dswm.methods.jtoratc.sca import TrajectoryProgram

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True, kw_only=True)
class JTORATCSettings:
    """JTORATC's settings (config.yaml ``methods.jtoratc``)."""

    w_delay: float = setting("nonnegative")
    """Weight of the delay term D (mean per-user delay of a slot's traffic, in slots)."""
    w_energy: float = setting("nonnegative")
    """Weight of the energy term E (the slot's propulsion power over the fleet's hover power)."""
    w_load: float = setting("nonnegative")
    """Weight of the load-imbalance term L (squared coefficient of variation of the UAVs' demand shares)."""
    bcd_iters: int = setting("count")
    """Most BCD rounds (association, bandwidth, trajectory) per solve."""
    bcd_tol: float = setting("nonnegative")
    """A round that lowers J by less than this fraction of it ends the BCD."""
    assoc_iters: int = setting("count")
    """Projected-gradient steps on the relaxed association per round."""
    sca_iters: int = setting("count")
    """Most SCA steps of the trajectory block per round."""
    sca_tol: float = setting("nonnegative")
    """An SCA step that lowers J by less than this fraction of it ends the trajectory block."""
    trust_region_m: float = setting("positive")
    """Trust-region radius of an SCA step around its expansion point (halved after a step that does not lower J)."""
    solver: str = setting(
        schema={"type": "string", "pattern": "^[A-Z_]+$",
                "description": "a cvxpy solver name in capitals, e.g. CLARABEL"})
    """cvxpy solver of the SCA step."""
    solve_budget_ms: float = setting("positive")
    """Degradation rule: once a solve takes longer than this (wall time), the rest of the day is degraded."""
    degrade_every: int = setting("count")
    """Slots per solve under the degradation rule; the plan is held in between."""
    degraded_sca_iters: int = setting("count")
    """SCA steps per round under the degradation rule."""

    def __post_init__(self):
        check_fields(self, "methods.jtoratc")
        if self.w_delay + self.w_energy + self.w_load <= 0:
            raise ConfigError(f"config key methods.jtoratc: expected w_delay, w_energy and w_load with a positive sum, "
                              f"found {self.w_delay}, {self.w_energy} and {self.w_load}")


class SlotPlan(NamedTuple):
    """Outcome of one solve."""

    pos: np.ndarray
    """(K, 2) planned positions after the slot, metres."""
    logit: np.ndarray
    """(K,) bandwidth logits."""
    trace: list[float]
    """J at the start and after each block of each round (blocks 1-2 together, then 3)."""
    rounds: int
    failures: int
    """SCA steps whose solver failed."""
    failure: str | None
    """The first failure's reason."""


def trajectory_block(slot: Slot, pos: np.ndarray, assoc: np.ndarray, share: np.ndarray, j_now: float, *,
                     program: TrajectoryProgram, bridges, steps: int, trust_m: float,
                     tol: float) -> tuple[np.ndarray, float, int, str | None]:
    """Up to ``steps`` SCA steps on the positions; returns (positions, J, solver failures, first failure)."""
    movable = slot.movable
    if not movable.any():
        return pos, j_now, 0, None
    cell = slot.has & movable[assoc]
    requested = np.where(cell, slot.requested, 1.0)
    radius = np.where(movable, slot.d_max_m, 0.0)
    for _ in range(steps):
        centre = np.where(movable[:, None], pos, slot.start)
        a, b = rate_surrogate(share, ((pos[assoc] - slot.cells) ** 2).sum(-1), slot.params, bridges)
        new, status = program.solve(start=slot.start, centre=centre, radius=radius, trust=trust_m,
                                    assoc=np.where(cell, assoc, -1), alpha=a / requested, beta=b / requested,
                                    demand=slot.x / slot.x.sum())
        if new is None:
            return pos, j_now, 1, status
        # Exactly inside D_max and the area (the solver meets its constraints to a tolerance).
        move = new - slot.start
        move *= np.minimum(1.0, slot.d_max_m / np.maximum(np.linalg.norm(move, axis=1, keepdims=True), 1e-12))
        new = np.clip(slot.start + move, 0.0, [slot.width_m, slot.height_m])
        new = np.where(movable[:, None], new, pos)
        j_new = objective(slot, new, assoc, share).total
        if j_new < j_now:
            gain, pos, j_now = j_now - j_new, new, j_new
            if gain <= tol * abs(j_now):
                break
        else:
            trust_m /= 2.0
    return pos, j_now, 0, None


def solve_slot(slot: Slot, settings: JTORATCSettings, *, program: TrajectoryProgram, bridges,
               sca_iters: int) -> SlotPlan:
    """JTORATC's BCD for one slot (module docstring)."""
    pos = slot.stay.copy()
    assoc = nearest(slot, pos)
    share = bandwidth_block(slot, pos, assoc)
    j_now = objective(slot, pos, assoc, share).total
    trace, failures, failure, moved, rounds = [j_now], 0, None, False, 0
    for rounds in range(1, settings.bcd_iters + 1):
        before = j_now
        # 1-2. Association by relaxation and rounding; the KKT bandwidth of the association kept.
        cand = association_block(slot, pos, assoc, iters=settings.assoc_iters)
        if moved:  # the positions changed: the KKT split of the current association at them
            s_new = bandwidth_block(slot, pos, assoc)
            j_new = objective(slot, pos, assoc, s_new).total
            if j_new < j_now:
                share, j_now = s_new, j_new
        if not np.array_equal(cand, assoc):
            s_new = bandwidth_block(slot, pos, cand)
            j_new = objective(slot, pos, cand, s_new).total
            if j_new < j_now:
                assoc, share, j_now = cand, s_new, j_new
        trace.append(j_now)
        # 3. Trajectory by SCA, association and bandwidth held.
        new, j_now, failed, why = trajectory_block(slot, pos, assoc, share, j_now, program=program, bridges=bridges,
                                                   steps=sca_iters, trust_m=settings.trust_region_m,
                                                   tol=settings.sca_tol)
        moved, pos = moved or not np.array_equal(new, pos), new
        failures, failure = failures + failed, failure or why
        trace.append(j_now)
        if before - j_now <= settings.bcd_tol * abs(before):
            break
    # Execution: the environment's nearest association, and the logit fitted to its KKT split.
    env = nearest(slot, pos)
    logit = fit_bandwidth_logit(slot, env, bandwidth_block(slot, pos, env))
    return SlotPlan(pos=pos, logit=logit, trace=trace, rounds=rounds, failures=failures, failure=failure)


class JTORATCController(Controller):
    """JTORATC (Sun et al. 2024) on the current observed map, with the paper's degradation rule.

    Not batched: each day solves its own convex programs. No random draw; only the degradation rule reads the
    clock, and :meth:`day_stats` reports how often it applied. Not ``deterministic``: the clock may change a day's
    plan (a first solve within the budget on a faster machine) and changes its solver counts, so every seed's
    evaluation runs on its own.

    Args:
        name, seed, device: see Controller.
        options: the settings.
    """

    options_type: ClassVar[type] = JTORATCSettings

    def __init__(self, *, name: str, seed: int = 0, device: str = "cpu", options: JTORATCSettings):
        super().__init__(name=name, seed=seed, device=device, options=options)
        self.program: TrajectoryProgram | None = None
        self._program_key: tuple | None = None

    def save(self, path) -> None:
        """Nothing to save: JTORATC learns nothing."""

    def load(self, path) -> None:
        """Nothing to load."""

    def reset(self, ctx: DayContext) -> None:
        """Keep the day's constants; build the SCA program for a new grid; the day's counters start at 0."""
        o, scn, geom = self.options, ctx.scenario, ctx.geometry
        self.ctx, self.grid, self.scenario, self.geom = ctx, ctx.grid, scn, geom
        self.cells = torch.as_tensor(ctx.cells).detach().cpu().double().numpy()
        self.params = ServiceParams.from_scenario(scn)
        self.bridges = concave_bridges(self.params, geom.width_m**2 + geom.height_m**2)
        key = (self.cells.tobytes(), scn.n_uavs, geom.width_m, geom.height_m, scn.rotor, scn.slot_s)
        if key != self._program_key:
            from dswm.methods.jtoratc.sca import TrajectoryProgram

            self.program = TrajectoryProgram(cells=self.cells, n_uavs=scn.n_uavs, width_m=geom.width_m,
                                             height_m=geom.height_m, rotor=scn.rotor, slot_s=scn.slot_s,
                                             weights=(o.w_delay, o.w_energy), solver=o.solver)
            self._program_key = key
        self.t, self.degraded, self.last_solve, self.warned = 0, False, 0, False
        self.target: np.ndarray | None = None
        self.logit: np.ndarray | None = None
        self.counts = {"solves": 0, "solver_failures": 0, "over_budget_solves": 0, "degraded_slots": 0,
                       "held_slots": 0}
        self.solve_ms: list[float] = []
        self.rounds: list[int] = []

    def act(self, obs: Mapping[str, Any]) -> np.ndarray:
        """(K, 3): a solve, or under the degradation rule between solves the held plan."""
        o = self.options
        state = fleet_state_from_obs(np.asarray(obs["fleet"])[None], self.grid, self.scenario)
        self.t += 1
        if self.degraded and self.t - self.last_solve < o.degrade_every:
            self.counts["held_slots"] += 1
            self.counts["degraded_slots"] += 1
        else:
            sca_iters = o.degraded_sca_iters if self.degraded else o.sca_iters
            t0 = time.perf_counter()
            self.target, self.logit = self._solve(obs, state, sca_iters)
            ms = 1000.0 * (time.perf_counter() - t0)
            self.counts["solves"] += 1
            self.counts["degraded_slots"] += int(self.degraded)
            self.solve_ms.append(ms)
            if ms > o.solve_budget_ms:
                self.counts["over_budget_solves"] += 1
                self.degraded = True
            self.last_solve = self.t
        move = to_action(torch.as_tensor(self.target), state.pos[0].double(), self.scenario.d_max_m)
        return np.clip(np.concatenate([move.numpy(), self.logit[:, None]], axis=1), -1.0, 1.0).astype(np.float32)

    def _solve(self, obs: Mapping[str, Any], state, sca_iters: int) -> tuple[np.ndarray, np.ndarray]:
        """Targets (K, 2) and logits (K,) of one solve; a UAV that does not follow this action: its own position,
        logit 0."""
        scn, k = self.scenario, self.scenario.n_uavs
        nxt, _ = fleet_step(state, torch.zeros(1, k, 3), self.geom, scn)
        avail = (nxt.status == ACTIVE)[0].numpy()
        movable = (state.status == ACTIVE)[0].numpy() & avail
        x = np.asarray(obs["demand"], dtype=np.float64)[-1].reshape(-1)
        x = np.where(x > DEMAND_EPS, x, 0.0)
        start, stay = state.pos[0].double().numpy(), nxt.pos[0].double().numpy()
        if not avail.any() or not (x > 0).any():
            return start, np.zeros(k)
        o = self.options
        slot = Slot(x=x, cells=self.cells, start=start, stay=stay, avail=avail,
                    movable=movable, params=self.params, rotor=scn.rotor, slot_s=scn.slot_s, d_max_m=scn.d_max_m,
                    width_m=self.geom.width_m, height_m=self.geom.height_m,
                    weights=(o.w_delay, o.w_energy, o.w_load))
        plan = solve_slot(slot, o, program=self.program, bridges=self.bridges, sca_iters=sca_iters)
        self.rounds.append(plan.rounds)
        if plan.failures:
            self.counts["solver_failures"] += plan.failures
            if not self.warned:
                log.warning("%s: the SCA solver failed on day %s, slot %d (%s); the trajectory block kept the last "
                            "positions. Later failures of this day are counted (days.parquet column "
                            "stat_solver_failures), not logged.", self.name, self.ctx.label, self.t, plan.failure)
                self.warned = True
        return np.where(movable[:, None], plan.pos, start), np.where(movable, plan.logit, 0.0)

    def day_stats(self) -> list[dict[str, float]]:
        """The day's solver counts: solves, solver_failures, over_budget_solves, degraded_slots (decisions under
        the degradation rule), held_slots (of which the plan was held), bcd_rounds_mean, solve_ms_median."""
        return [{**{key: float(v) for key, v in self.counts.items()},
                 "bcd_rounds_mean": float(np.mean(self.rounds)) if self.rounds else 0.0,
                 "solve_ms_median": float(np.median(self.solve_ms)) if self.solve_ms else 0.0}]
