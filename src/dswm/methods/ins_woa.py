"""INS-WOA (Jia et al. 2025), re-implemented: K-means/Voronoi pre-deployment, then a non-dominated-sorting whale
optimization of the fleet every slot (docs/PROTOCOL.md §5).

* Pre-deployment: the K-means centres of the mean TRAINING map (``DayContext.init_pos``, the positions Static
  holds; this method sees nothing else of the training days). Their Voronoi partition of the grid gives each UAV
  a region: the cells whose nearest centre is its own. A UAV's decision variable is a target point inside the
  bounding box of its region, widened by ``region_margin_cells`` cells and clipped to the area; it flies towards
  the target, at most D_max per slot (``to_action``, as Greedy and Static convert targets).
* Per slot: :func:`woa_search` over the whole fleet, K targets and K bandwidth logits in [-1, 1], with three
  objectives scored by ONE batched call of the physics per iteration for every (day, whale): served ratio on the
  current observed map x_t (maximized), fleet energy of the move under ``dswm.sim.fleet.fleet_step`` (minimized)
  and load imbalance, the coefficient of variation of the per-UAV served load sum_{g -> k} x_g f_g over the UAVs
  that can serve after the move (minimized). The population starts with the pre-deployment (every UAV towards its
  K-means centre, logits 0), the fleet held where it is (targets clamped into the regions, logits 0) and
  uniform draws in the boxes.
* The leader (the whale every other one encircles or spirals around, and the executed action after the last
  iteration) is the whale of the first front with the best served ratio, ties to the lower fleet energy, then to
  the lower imbalance; NSGA-II crowding decides which whales of the last admitted front survive.
"""
from __future__ import annotations

import dataclasses
import math
import time
from typing import Any, Callable, ClassVar, Mapping, NamedTuple, Sequence

import numpy as np
import torch
from pymoo.operators.survival.rank_and_crowding.metrics import get_crowding_function
from pymoo.util.nds.non_dominated_sorting import NonDominatedSorting

from dswm.config import check_fields, setting, stable_hash
from dswm.methods.base import DayContext
from dswm.methods.classical import BatchedController
from dswm.methods.search import to_action
from dswm.sim.core import fleet_state_from_obs
from dswm.sim.fleet import ACTIVE, FleetState, Geometry, fleet_step
from dswm.sim.physics import DEMAND_EPS, ServiceParams, service, sum_per_uav
from dswm.sim.scenario import Scenario

SPIRAL_B = 1.0
"""Shape constant b of the logarithmic spiral (the standard WOA's b = 1)."""

_SORTING = NonDominatedSorting()
_CROWDING = get_crowding_function("cd")  # NSGA-II crowding distance


@dataclasses.dataclass(frozen=True, kw_only=True)
class InsWoaSettings:
    """Strength of the per-slot whale optimization (config.yaml ``methods.ins_woa``)."""

    population: int = setting(schema={"type": "integer", "minimum": 4, "description": "an integer >= 4"})
    """Whales per day and slot (at least 4: two seeds and two random whales)."""
    iterations: int = setting("count")
    """WOA iterations per slot; each scores ``population`` new fleets per day in one physics call."""
    region_margin_cells: float = setting("nonnegative")
    """Cells by which a UAV's Voronoi bounding box is widened on every side (0: the region's own cells only)."""

    def __post_init__(self):
        check_fields(self, "methods.ins_woa")


class WoaResult(NamedTuple):
    """Outcome of :func:`woa_search` for B independent problems."""

    x: torch.Tensor
    """(B, D) the leader of the final population."""
    f: torch.Tensor
    """(B, M) its objectives."""
    population: torch.Tensor
    """(B, N, D) the final population."""
    objectives: torch.Tensor
    """(B, N, M) its objectives."""


def survive(f: np.ndarray, n: int) -> tuple[np.ndarray, int]:
    """NSGA-II survival of one problem: fronts by pymoo's non-dominated sorting, the front that does not fit
    whole cut by pymoo's crowding distance (larger first; equal distances keep the lower index).

    Args:
        f: (P, M) objectives to minimize.
        n: survivors, at most P.

    Returns:
        (n,) indices of the survivors and the index of the leader: the point of the first front with the lowest
        first objective, ties to the lowest second objective, and so on, then to the lower index. (pymoo's
        crowding gives the first of equal points an infinite distance, so it would break such ties by index.)
    """
    fronts = _SORTING.do(f, n_stop_if_ranked=n)
    first = fronts[0]
    leader = int(first[np.lexsort((first, *(f[first, j] for j in reversed(range(f.shape[1])))))[0]])
    parts: list[np.ndarray] = []
    left = n
    for front in fronts:
        if left <= 0:
            break
        if len(front) > left:
            cd = _CROWDING.do(f[front], n_remove=len(front) - left)
            front = front[np.argsort(-cd, kind="stable")[:left]]
        parts.append(front)
        left -= len(front)
    keep = np.concatenate(parts)
    if leader not in keep:  # cut with a crowded front (it ties with a point placed first): it survives anyway
        keep[-1] = leader
    return keep, leader


def woa_move(pop: torch.Tensor, leader: torch.Tensor, a: float, r1: torch.Tensor, r2: torch.Tensor,
             p: torch.Tensor, l: torch.Tensor, partner: torch.Tensor) -> torch.Tensor:
    """One standard WOA step of every whale (Mirjalili and Lewis 2016, eqs. 2.1-2.8) in the unit box.

    A = 2 a r1 - a and C = 2 r2 are coefficient vectors (one draw per whale and coordinate, the paper's vector
    form; the |A| test is made per coordinate). With probability 1/2 (p < 0.5) a coordinate encircles the
    leader's, X' = X* - A |C X* - X|, where |A| < 1, and searches around a random whale's where |A| >= 1,
    X' = X_rand - A |C X_rand - X|; otherwise the whale follows the logarithmic spiral around the leader,
    X' = |X* - X| e^{b l} cos(2 pi l) + X*, with b = 1 and l uniform in [-1, 1] per whale. The result is clipped
    to [0, 1].

    Args:
        pop: (B, N, D) whales in [0, 1]^D.
        leader: (B, D) the leader of each problem.
        a: the control parameter, 2 at the first iteration falling linearly towards 0.
        r1, r2: (B, N, D) uniforms in [0, 1).
        p: (B, N, 1) uniforms: spiral when p >= 0.5.
        l: (B, N, 1) uniforms in [-1, 1].
        partner: (B, N) index of each whale's random whale.

    Returns:
        (B, N, D) the moved whales.
    """
    big_a = 2.0 * a * r1 - a
    c = 2.0 * r2
    lead = leader.unsqueeze(1).expand_as(pop)
    rand = torch.gather(pop, 1, partner.unsqueeze(-1).expand_as(pop))
    ref = torch.where(big_a.abs() >= 1.0, rand, lead)
    encircle = ref - big_a * (c * ref - pop).abs()
    spiral = (lead - pop).abs() * torch.exp(SPIRAL_B * l) * torch.cos(2.0 * math.pi * l) + lead
    return torch.where(p < 0.5, encircle, spiral).clamp(0.0, 1.0)


def woa_search(objective: Callable[[torch.Tensor], torch.Tensor], lower: torch.Tensor, upper: torch.Tensor, *,
               population: int, iterations: int, generators: Sequence[torch.Generator],
               init: torch.Tensor | None = None) -> WoaResult:
    """Non-dominated-sorting whale optimization of B independent box-bounded problems at once.

    Per iteration t = 0..T-1 (a = 2 - 2t/T): every whale moves by :func:`woa_move` towards (or around) the leader;
    the N moved whales of every problem are scored by ONE call of ``objective``; parents and offspring (2N) are
    reduced to N by :func:`survive`, which also names the next leader. A single objective (M = 1) makes it an
    elitist WOA. The search runs in unit coordinates u = (x - lower) / (upper - lower).

    Args:
        objective: (B, N, D) points -> (B, N, M) objectives to MINIMIZE; the first is the leader's criterion.
        lower, upper: (B, D) the box of each problem (upper >= lower).
        population: N whales per problem.
        iterations: T.
        generators: B torch generators, one per problem: a problem's draws do not depend on the others.
        init: optional (B, S, D) points, S <= N, placed first in the initial population; the rest is uniform.

    Returns:
        WoaResult.
    """
    b, d = lower.shape
    if len(generators) != b:
        raise ValueError(f"woa_search: expected {b} generators (one per problem), found {len(generators)}")
    span = (upper - lower).clamp_min(0.0)

    def to_x(u: torch.Tensor) -> torch.Tensor:
        return lower.unsqueeze(1) + u * span.unsqueeze(1)

    # Initial population: the given seeds, then uniform points of the box.
    u = torch.stack([torch.rand(population, d, generator=g) for g in generators])  # (B, N, D)
    if init is not None:
        s = init.shape[1]
        if s > population:
            raise ValueError(f"woa_search: {s} initial points exceed the population {population}")
        u[:, :s] = ((init - lower.unsqueeze(1)) / span.clamp_min(1e-12).unsqueeze(1)).clamp(0.0, 1.0)
    f = objective(to_x(u))
    rows = torch.arange(b).unsqueeze(1)
    leader = torch.empty(b, dtype=torch.long)
    for i in range(b):
        leader[i] = survive(f[i].double().numpy(), population)[1]

    for t in range(iterations):
        # Move every whale (standard WOA update, draws per problem from its own generator).
        a = 2.0 - 2.0 * t / iterations
        draws = torch.stack([torch.rand(population, 2 * d + 2, generator=g) for g in generators])
        partner = torch.stack([torch.randint(population, (population,), generator=g) for g in generators])
        r1, r2, p, l = draws[..., :d], draws[..., d:2 * d], draws[..., 2 * d:2 * d + 1], draws[..., 2 * d + 1:]
        child = woa_move(u, u[torch.arange(b), leader], a, r1, r2, p, 2.0 * l - 1.0, partner)
        # Score the offspring of every problem in one call.
        f_child = objective(to_x(child))
        # NSGA-II survival over parents and offspring; the leader comes from the first front.
        u_all, f_all = torch.cat([u, child], 1), torch.cat([f, f_child], 1)
        keep = torch.empty(b, population, dtype=torch.long)
        for i in range(b):
            idx, lead = survive(f_all[i].double().numpy(), population)
            keep[i] = torch.from_numpy(idx)
            leader[i] = int(np.flatnonzero(idx == lead)[0])
        u, f = u_all[rows, keep], f_all[rows, keep]
    best = torch.arange(b)
    return WoaResult(x=to_x(u)[best, leader], f=f[best, leader], population=to_x(u), objectives=f)


def voronoi_boxes(anchors: torch.Tensor, cells: torch.Tensor, cell_m: float, margin_cells: float,
                  width_m: float, height_m: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Bounding boxes of the Voronoi regions of the K-means centres on the grid.

    A cell belongs to the region of its nearest centre (ties to the lower index, as the association). A box spans
    its region's cells (their edges, not only their centres) and the centre itself, widened by ``margin_cells``
    cells on every side and clipped to the area.

    Args:
        anchors: (K, 2) K-means centres in metres.
        cells: (G, 2) cell centres.
        cell_m: cell side.
        margin_cells: widening in cells.
        width_m, height_m: the area.

    Returns:
        (K, 2) lower and (K, 2) upper corners in metres.
    """
    owner = torch.cdist(cells.double(), anchors.double()).argmin(dim=1)  # (G,)
    lo, hi = anchors.double().clone(), anchors.double().clone()
    for k in range(anchors.shape[0]):
        mine = cells[owner == k].double()
        if len(mine):
            lo[k] = torch.minimum(lo[k], mine.min(0).values)
            hi[k] = torch.maximum(hi[k], mine.max(0).values)
    pad = (0.5 + margin_cells) * cell_m
    area = torch.tensor([width_m, height_m], dtype=torch.float64)
    return (lo - pad).clamp(min=0.0).float(), torch.minimum(hi + pad, area).float()


def fleet_objectives(state: FleetState, x: torch.Tensor, target: torch.Tensor, logit: torch.Tensor, *,
                     cells: torch.Tensor, geom: Geometry, scenario: Scenario, params: ServiceParams) -> torch.Tensor:
    """The three objectives (to minimize) of N candidate plans, scored by one call of the physics.

    Each UAV flies towards its target, at most D_max (``to_action``, then ``fleet_step``, which also says which UAVs
    can serve after the move and what the move costs). Objectives: minus the served ratio of ``x`` by the moved
    fleet with the plan's bandwidth logits; the fleet energy of the slot in joules; the load imbalance, the
    coefficient of variation (population std / mean) of the served load sum_{g -> k} x_g f_g over the UAVs that
    can serve (0 when nothing is served).

    Args:
        state: the fleet now, leading shape (N,).
        x: (N, G) the map each candidate is scored on.
        target: (N, K, 2) target points in metres.
        logit: (N, K) bandwidth logits in [-1, 1].
        cells: (G, 2) cell centres.
        geom, scenario, params: the area, the constants and the service parameters.

    Returns:
        (N, 3): -served ratio, fleet energy (J), load imbalance.
    """
    k = target.shape[1]
    action = torch.cat([to_action(target, state.pos, scenario.d_max_m), logit.unsqueeze(-1)], -1)
    nxt, energy = fleet_step(state, action, geom, scenario)
    avail = nxt.status == ACTIVE
    res = service(x, nxt.pos, avail, cells, params=params, bw_logit=logit)
    load = sum_per_uav(x * res.fulfilment, res.assoc, k) * avail  # (N, K) served load per UAV
    count = avail.sum(-1).clamp_min(1)
    mean = load.sum(-1) / count
    var = ((load - mean.unsqueeze(-1)) ** 2 * avail).sum(-1) / count
    cv = torch.where(mean > 0, var.sqrt() / mean.clamp_min(1e-12), torch.zeros_like(mean))
    return torch.stack([-res.sr, energy.sum(-1), cv], -1)


class InsWoaController(BatchedController):
    """INS-WOA: Voronoi-bounded non-dominated-sorting whale optimization per slot (module docstring).

    Args:
        name, device: see Controller.
        seed: the job's seed; each day's generator is seeded from it, the dataset and the day label.
        options: the search's size.
    """

    options_type: ClassVar[type] = InsWoaSettings

    def __init__(self, *, name: str, seed: int = 0, device: str = "cpu", options: InsWoaSettings):
        super().__init__(name=name, seed=seed, device=device, options=options)

    def reset_batch(self, ctxs: Sequence[DayContext]) -> None:
        """Voronoi boxes of the pre-deployment and one generator per day."""
        c = ctxs[0]
        self.grid, self.scenario, self.geom = c.grid, c.scenario, c.geometry
        self.cells = torch.as_tensor(c.cells, dtype=torch.float32)
        self.params = ServiceParams.from_scenario(c.scenario)
        self.anchors = torch.as_tensor(np.stack([x.init_pos for x in ctxs]), dtype=torch.float32)  # (B, K, 2)
        boxes = [voronoi_boxes(a, self.cells, c.grid.cell_m, self.options.region_margin_cells,
                               self.geom.width_m, self.geom.height_m) for a in self.anchors]
        self.box_lo = torch.stack([lo for lo, _ in boxes])  # (B, K, 2)
        self.box_hi = torch.stack([hi for _, hi in boxes])
        self.solve_ms: list[float] = []  # wall time of each slot's search per day of the batch
        self.generators = []
        for x in ctxs:
            g = torch.Generator()
            g.manual_seed(int(stable_hash({"method": "ins_woa", "seed": self.seed, "dataset": x.dataset,
                                           "day": str(x.label)}), 16) % 2**63)
            self.generators.append(g)

    def act_batch(self, obs: Mapping[str, Any]) -> np.ndarray:
        """(B, K, 3) actions of one slot for B days; the search's wall time per day is recorded (day_stats)."""
        start = time.perf_counter()
        out = self._act(obs)
        self.solve_ms.append(1000.0 * (time.perf_counter() - start) / out.shape[0])
        return out

    def day_stats(self) -> list[dict[str, float]]:
        """Per day of the batch: solve_ms_median, the median over slots of the search's ms per day-slot (the batch
        is searched as one, so every day of a batch reports the same), and solves. INS-WOA has no degradation
        rule: every slot runs the full search."""
        med = float(np.median(self.solve_ms)) if self.solve_ms else 0.0
        return [{"solve_ms_median": med, "solves": float(len(self.solve_ms))} for _ in self.generators]

    def _act(self, obs: Mapping[str, Any]) -> np.ndarray:
        demand = torch.as_tensor(np.asarray(obs["demand"]))
        x = demand[:, -1].reshape(demand.shape[0], -1).float()  # (B, G) the current observed map x_t
        state = fleet_state_from_obs(obs["fleet"], self.grid, self.scenario)
        b, k = state.status.shape
        # Cells without demand on every day of the batch change no objective: score on the others only.
        cols = (x > DEMAND_EPS).any(0).nonzero().squeeze(-1)
        x, cells = x[:, cols], self.cells[cols]
        n = self.options.population
        # The fleet state and the map once per whale, for every call of the objective (N whales per day).
        many = FleetState(*(v.repeat_interleave(n, dim=0) for v in state))
        x_n = x.repeat_interleave(n, dim=0)

        def objective(z: torch.Tensor) -> torch.Tensor:
            """(B, N, 3K) targets and logits -> (B, N, 3) objectives of every (day, whale)."""
            target, logit = z[..., :2 * k].reshape(b * n, k, 2), z[..., 2 * k:].reshape(b * n, k)
            return fleet_objectives(many, x_n, target, logit, cells=cells, geom=self.geom, scenario=self.scenario,
                                    params=self.params).reshape(b, n, 3)

        ones = torch.ones(b, k)
        lower = torch.cat([self.box_lo.reshape(b, 2 * k), -ones], -1)
        upper = torch.cat([self.box_hi.reshape(b, 2 * k), ones], -1)
        hold = torch.minimum(torch.maximum(state.pos, self.box_lo), self.box_hi)
        init = torch.stack([torch.cat([self.anchors.reshape(b, 2 * k), 0 * ones], -1),
                            torch.cat([hold.reshape(b, 2 * k), 0 * ones], -1)], 1)  # (B, 2, 3K)
        with torch.no_grad():
            if cols.numel() == 0:  # nothing to serve: fly towards the pre-deployment
                best = init[:, 0]
            else:
                best = woa_search(objective, lower, upper, population=n, iterations=self.options.iterations,
                                  generators=self.generators, init=init).x
        move = to_action(best[:, :2 * k].reshape(b, k, 2), state.pos, self.scenario.d_max_m)
        move = move * (state.status == ACTIVE).unsqueeze(-1)  # only active UAVs follow an action
        return torch.cat([move, best[:, 2 * k:].unsqueeze(-1)], -1).clamp(-1.0, 1.0).numpy()
