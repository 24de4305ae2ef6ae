"""The per-slot ceiling (``ceiling``, clairvoyant upper bound; docs/PROTOCOL.md §5, "The per-slot ceiling").

Not a controller that flies a fleet: before each slot t >= 1 it places the whole fleet anew for that slot's TRUE map
x_t, with no motion limit and every UAV available, and the evaluation serves the placement with the environment's
own physics (``dswm.sim.core.FleetCore.place``: every UAV active, no flight, no energy). Slot 0 is served by the
initial deployment, as for every method. A controller's fleet at slot t is one placement of at most K available
UAVs with logits in [-1, 1], which K available UAVs can copy (an unavailable UAV parked on an available one serves
nothing: ties go to the lower index), so no controller serves more in a slot than the best placement for that
slot's map, and no day's mean more than the ceiling's, up to how close the search comes to that best placement.

The search, :func:`ceiling_search`, is stronger than the shared ``search`` (``dswm.methods.search.bcd_search``) of
the controllers: a UAV may jump anywhere (a lattice over the whole area, not one slot's reach), several lattice
points are refined, the logit is searched and refined after every move, passes go on until one moves nothing, and
every slot starts from several placements: the best ones of the slot before (``chains``) and ones built from the
slot's map alone (``fresh``: its demand-weighted K-means from the initial deployment, then from placements drawn
by a generator seeded by the dataset and the day alone, so every seed of a job gives the same numbers). Its
settings, :class:`CeilingSettings`, are config.yaml ``ceiling``; ``benchmarks/bench_ceiling.py`` measures what
doubling them changes on TRAINING days.
"""
from __future__ import annotations

import dataclasses
import functools
from typing import Any, ClassVar, Collection, Mapping, Sequence

import numpy as np
import torch

from dswm.config import check_fields, setting, stable_hash, with_budget
from dswm.methods.base import DayContext
from dswm.methods.classical import BatchedController
from dswm.sim.fleet import Geometry
from dswm.sim.physics import DEMAND_EPS, ServiceParams, associate, served_ratio, sum_per_uav


@dataclasses.dataclass(frozen=True, kw_only=True)
class CeilingSettings:
    """Strength of the ceiling's per-slot search (config.yaml ``ceiling``)."""

    sweeps: int = setting("count")
    """Passes over the UAVs per start at most; the search stops after a pass that moved nothing."""
    lattice: int = setting(schema={"type": "integer", "minimum": 2, "description": "an integer >= 2"})
    """Points per axis of the lattice over the WHOLE area (cell-centred: (i + 1/2) W / lattice) a UAV may jump to."""
    keep: int = setting("count")
    """Best lattice points refined per move of a UAV (several basins, not only the best point's)."""
    refine: int = setting("natural")
    """Rounds of local refinement of each kept point (on its 8 neighbours at half the previous spacing) and of the
    chosen logit (on its 2 neighbours at half the previous step of ``bw_logits``)."""
    polish: int = setting("natural")
    """Further rounds of refinement for the slot's best placement alone: once every start is searched, the best one
    is searched again from itself with ``refine + polish`` rounds (spacings and logit steps down to 2^-(refine +
    polish) of the lattice's and the logit set's), so the bound's resolution is fine where it matters at the cost of
    one start."""
    chains: int = setting("count")
    """Best placements of a slot carried to the next as starts (at slot 1: the initial deployment)."""
    fresh: int = setting("count")
    """Starts of each slot built from its map alone: its demand-weighted K-means from the initial deployment, then
    K-means from placements drawn from the map."""
    bw_logits: tuple[float, ...] = setting(schema={
        "type": "array", "items": {"type": "number", "minimum": -1, "maximum": 1}, "minItems": 1,
        "contains": {"const": 0},
        "description": "a non-empty list of bandwidth logits in [-1, 1] that includes 0"})
    """Bandwidth logits searched per UAV after each of its moves (the controllers' range is [-1, 1])."""

    section: ClassVar[str] = "ceiling"
    """The config key of the section, for messages."""

    def __post_init__(self):
        check_fields(self, self.section)
        # 0 first, so a tie keeps the demand-proportional split.
        object.__setattr__(self, "bw_logits", tuple(sorted((float(v) for v in self.bw_logits), key=abs)))

    def doubled(self, only: Collection[str] | None = None) -> "CeilingSettings":
        """Every setting doubled: twice the sweeps, kept points, refinement rounds, chains and fresh starts, a lattice
        of twice the points per axis and a logit set of twice the resolution (the convergence check,
        ``benchmarks/bench_ceiling.py``); or only the settings named in ``only`` (which one carries a rise)."""
        names = [f.name for f in dataclasses.fields(self)]
        unknown = sorted(set(only or ()) - set(names))
        if unknown:
            raise ValueError(f"{self.section}: cannot double {unknown}; the settings are {names}")
        levels = sorted(set(self.bw_logits))
        mids = [(a + b) / 2 for a, b in zip(levels, levels[1:])]
        twice = {name: 2 * getattr(self, name) for name in names if name != "bw_logits"}  # polish 0 stays 0
        twice["bw_logits"] = tuple(levels + mids)
        return dataclasses.replace(self, **{k: v for k, v in twice.items() if only is None or k in only})


CHUNK_FLEETS = 256
"""Fleets per call of the physics at most: past ~256 fleets of 400 cells a call costs more per fleet (12-15 us up to
256, 24 us from 512 on one thread of the development machine)."""
MIN_GAIN = 1e-5
"""A move, a refinement step or a logit must raise the served ratio by more than this (float32 resolution of a
served ratio summed over hundreds of cells is ~1e-7): smaller gains are noise, and a search that chases them does
not stop."""
LLOYD_ITERATIONS = 10
"""Weighted Lloyd iterations that turn a start into a demand-weighted K-means of the slot's map."""

_RING = torch.tensor([[-1, -1], [-1, 0], [-1, 1], [0, -1], [0, 1], [1, -1], [1, 0], [1, 1]], dtype=torch.float32)
"""The 8 lattice neighbours of a point (refinement rounds)."""


@functools.lru_cache(maxsize=8)
def area_lattice(points: int, width_m: float, height_m: float) -> torch.Tensor:
    """(points^2, 2) float32 cell-centred lattice over the area: ((i + 1/2) W / points, (j + 1/2) H / points).
    Cached: every slot asks for the same one, and no caller writes into it."""
    xs = (torch.arange(points, dtype=torch.float64) + 0.5) * width_m / points
    ys = (torch.arange(points, dtype=torch.float64) + 0.5) * height_m / points
    return torch.stack(torch.meshgrid(xs, ys, indexing="ij"), dim=-1).reshape(-1, 2).float()


def ceiling_search(x: torch.Tensor, starts: torch.Tensor, start_logits: torch.Tensor, *, settings: CeilingSettings,
                   cells: torch.Tensor, geom: Geometry,
                   params: ServiceParams) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Block-coordinate ascent of the served ratio of one slot from S starts, for B days, every UAV available.

    From each start, passes over the UAVs until one moves nothing (at most ``sweeps``): UAV j takes the best of its
    current point and the whole-area lattice (others held), where the ``keep`` best lattice points are each refined
    over ``refine`` rounds on their 8 neighbours at half the previous spacing; then the best of its current logit
    and ``bw_logits``. A candidate must beat the current point (ties keep it), so the served ratio never falls
    below the start's, and a (day, start) whose pass moved nothing is at a local optimum of these moves and is left
    alone. Candidates are scored by ``dswm.sim.physics.served_ratio``, many (start, candidate) fleets a call. Each
    day is searched on its own, on the cells that carry demand in its map (the others change no served ratio), so a
    day's placement depends on that day alone, never on the days evaluated beside it (which cells are left out
    changes the float rounding of the sums, and with it which of two near-equal candidates wins).

    Args:
        x: (B, G) the true map of the slot.
        starts: (B, S, K, 2) start placements in metres; start_logits: (B, S, K) their bandwidth logits.
        settings: the search's strength.
        cells: (G, 2) cell centres in metres; geom, params: the area and the service constants.

    Returns:
        The placement (B, S, K, 2) reached from each start, its logits (B, S, K) and its served ratio (B, S).
    """
    b, s, k, _ = starts.shape
    if b > 1:  # each day on its own cells: see above
        days = [ceiling_search(x[i:i + 1], starts[i:i + 1], start_logits[i:i + 1], settings=settings, cells=cells,
                               geom=geom, params=params) for i in range(b)]
        return tuple(torch.cat(part) for part in zip(*days))
    plan = geom.clip(starts.reshape(b * s, k, 2).float()).clone()  # (N, K, 2), N = B x S rows
    logit = start_logits.reshape(b * s, k).float().clone()
    cols = (x[0] > DEMAND_EPS).nonzero().squeeze(-1)  # cells without demand change nothing
    if cols.numel() == 0:
        return plan.reshape(b, s, k, 2), logit.reshape(b, s, k), torch.ones(b, s)
    x, cells = x[:, cols].repeat_interleave(s, dim=0), cells[cols]  # (N, G')
    search = _Sweep(settings=settings, cells=cells, geom=geom, params=params)
    # A start that already serves the whole map is left alone: no move can gain more than MIN_GAIN on 1.0, so the
    # search would move nothing there (holiday and sparse slots, where most starts serve everything).
    active = torch.arange(b * s)[search.score(x, plan.unsqueeze(1), logit.unsqueeze(1)).squeeze(1) < 1.0]
    for _ in range(settings.sweeps):
        if active.numel() == 0:
            break
        p, lg = search(x[active], plan[active], logit[active])
        moved = (p != plan[active]).any(dim=2).any(dim=1) | (lg != logit[active]).any(dim=1)
        plan[active], logit[active] = p, lg
        active = active[moved]
    sr = search.score(x, plan.unsqueeze(1), logit.unsqueeze(1)).reshape(b, s)
    return plan.reshape(b, s, k, 2), logit.reshape(b, s, k), sr


class _Sweep:
    """One pass over the UAVs of :func:`ceiling_search` for N rows (a (day, start) each)."""

    def __init__(self, *, settings: CeilingSettings, cells: torch.Tensor, geom: Geometry, params: ServiceParams):
        self.settings, self.cells, self.geom, self.params = settings, cells, geom, params
        self.lattice = area_lattice(settings.lattice, geom.width_m, geom.height_m)
        self.spacing = torch.tensor([geom.width_m, geom.height_m]) / settings.lattice
        self.levels = torch.tensor(settings.bw_logits, dtype=torch.float32)
        gaps = torch.diff(torch.unique(self.levels))
        self.logit_step = float(gaps.min()) if gaps.numel() else 1.0  # the set's resolution, halved by each round

    def score(self, x: torch.Tensor, fleets: torch.Tensor, logits: torch.Tensor) -> torch.Tensor:
        """(N, C) served ratio of C candidate fleets (N, C, K, 2) with logits (N, C, K) on the maps x (N, G), in calls
        of at most CHUNK_FLEETS fleets (a fleet's score does not depend on the others of its call)."""
        n, c, k, _ = fleets.shape
        step = max(1, CHUNK_FLEETS // n)
        out, rows = [], {}
        for lo in range(0, c, step):
            m = min(step, c - lo)
            if m not in rows:  # per-candidate copies of the maps and availability, made once per size
                rows[m] = (x.repeat_interleave(m, dim=0), torch.ones(n * m, k, dtype=torch.bool))
            x_c, avail_c = rows[m]
            out.append(served_ratio(x_c, fleets[:, lo:lo + m].reshape(n * m, k, 2), avail_c, self.cells,
                                    params=self.params, bw_logit=logits[:, lo:lo + m].reshape(n * m, k)).reshape(n, m))
        return torch.cat(out, dim=1)

    def __call__(self, x: torch.Tensor, plan: torch.Tensor, logit: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The rows' placements (N, K, 2) and logits (N, K) after one pass over the UAVs from ``plan``, ``logit``."""
        plan, logit = plan.clone(), logit.clone()
        n, k, _ = plan.shape
        rows_n = torch.arange(n).unsqueeze(1)

        def scores(j: int, cand: torch.Tensor) -> torch.Tensor:
            """(N, C) served ratio with UAV j at each of the points ``cand`` (N, C, 2), the others at ``plan``."""
            fleets = plan.unsqueeze(1).expand(n, cand.shape[1], k, 2).clone()
            fleets[:, :, j] = cand
            return self.score(x, fleets, logit.unsqueeze(1).expand(n, cand.shape[1], k))

        for j in range(k):
            # The UAV's current point first, then the whole-area lattice: the `keep` best points are refined.
            cand = torch.cat([plan[:, j:j + 1], self.lattice.expand(n, -1, 2)], dim=1)  # (N, 1 + L, 2)
            sr = scores(j, cand)
            here = sr[:, 0]
            best_sr, top = sr.topk(min(self.settings.keep, sr.shape[1]), dim=1)  # (N, M)
            best = cand[rows_n, top]  # (N, M, 2)
            m = best.shape[1]
            for r in range(1, self.settings.refine + 1):
                near = self.geom.clip(best.unsqueeze(2) + self.spacing / 2**r * _RING)  # (N, M, 8, 2)
                near_sr, idx = scores(j, near.reshape(n, m * 8, 2)).reshape(n, m, 8).max(dim=2)
                better = near_sr > best_sr + MIN_GAIN  # a neighbour must beat the point it surrounds
                best = torch.where(better.unsqueeze(-1), near[rows_n, torch.arange(m), idx], best)
                best_sr = torch.where(better, near_sr, best_sr)
            top_sr, first = best_sr.max(dim=1)
            moved = top_sr > here + MIN_GAIN  # ties keep the UAV where it is
            plan[:, j] = torch.where(moved.unsqueeze(-1), best[torch.arange(n), first], plan[:, j])
            # Its bandwidth logit: the current one first (ties keep it), then the set, then finer rounds.
            cand = torch.cat([logit[:, j:j + 1], self.levels.expand(n, -1)], dim=1)  # (N, 1 + V)
            lg = logit.unsqueeze(1).expand(n, cand.shape[1], k).clone()
            lg[:, :, j] = cand
            sr = self.score(x, plan.unsqueeze(1).expand(n, cand.shape[1], k, 2), lg)
            top_sr, idx = sr.max(dim=1)
            idx = torch.where(top_sr > sr[:, 0] + MIN_GAIN, idx, torch.zeros_like(idx))
            best, best_sr = cand[torch.arange(n), idx], sr[torch.arange(n), idx]
            # then `refine` rounds on the two neighbours at half the previous step, within [-1, 1]
            for r in range(1, self.settings.refine + 1):
                near = (best.unsqueeze(1) + self.logit_step / 2**r * torch.tensor([-1.0, 1.0])).clamp(-1.0, 1.0)
                lg = logit.unsqueeze(1).expand(n, 2, k).clone()
                lg[:, :, j] = near
                near_sr, idx = self.score(x, plan.unsqueeze(1).expand(n, 2, k, 2), lg).max(dim=1)
                better = near_sr > best_sr + MIN_GAIN
                best = torch.where(better, near[torch.arange(n), idx], best)
                best_sr = torch.where(better, near_sr, best_sr)
            logit[:, j] = best
        return plan, logit


def lloyd(x: torch.Tensor, pos: torch.Tensor, cells: torch.Tensor, iterations: int) -> torch.Tensor:
    """(B, K, 2) demand-weighted K-means of the maps ``x`` (B, G) from ``pos`` (B, K, 2): each iteration moves every
    UAV to the demand-weighted centroid of the cells nearest to it (``dswm.sim.physics.associate``); a UAV that
    is nearest to no demand stays."""
    k = pos.shape[1]
    avail = torch.ones(pos.shape[:2], dtype=torch.bool)
    for _ in range(iterations):
        assoc = associate(pos, avail, cells)
        mass = sum_per_uav(x, assoc, k).unsqueeze(-1)  # (B, K, 1)
        centroid = torch.stack([sum_per_uav(x * cells[:, 0], assoc, k), sum_per_uav(x * cells[:, 1], assoc, k)], -1)
        pos = torch.where(mass > 0, centroid / mass.clamp_min(1e-12), pos)
    return pos


def draw_placements(rng: np.random.Generator, x: np.ndarray, cells: np.ndarray, k: int, count: int) -> np.ndarray:
    """(count, K, 2) placements of K UAVs on cell centres drawn with probability proportional to the demand of the
    map ``x`` (G,) (without replacement while enough cells carry demand)."""
    w = np.where(x > DEMAND_EPS, x, 0.0).astype(np.float64)
    if w.sum() <= 0:
        w = np.ones_like(w)
    p = w / w.sum()
    replace = int((p > 0).sum()) < k
    return np.stack([cells[rng.choice(len(p), size=k, replace=replace, p=p)] for _ in range(count)])


class CeilingController(BatchedController):
    """The per-slot ceiling: the best placement of the whole fleet for each slot's TRUE map (docs/PROTOCOL.md §5).

    It flies no fleet (``places = True``): the evaluation asks :meth:`place_batch` for each slot's placement and
    serves it with every UAV available and no motion limit (``FleetCore.place``).

    Args:
        name, seed, device: see Controller.
        options: the search's strength (config.yaml ``ceiling``).
    """

    clairvoyant = True
    places = True
    deterministic = True
    options_type: ClassVar[type] = CeilingSettings

    def __init__(self, *, name: str, seed: int = 0, device: str = "cpu", options: CeilingSettings):
        super().__init__(name=name, seed=seed, device=device, options=options)

    @classmethod
    def options_from_config(cls, *, name: str, config: Mapping[str, Any], profile: str) -> CeilingSettings:
        """The ceiling's own search (config.yaml ``ceiling``) with its ``ceiling.budgets.<profile>`` entry merged in:
        the demo and the paper run the section's settings, which pass the doubling check; only the smoke profile
        (CI) lowers them."""
        section, key = with_budget(config["ceiling"], profile, "ceiling")
        return cls.options_from_plain(name=name, data=section, where=key)

    def reset_batch(self, ctxs: Sequence[DayContext]) -> None:
        """Take each day's true demand (T, R, C) from the context (handed to clairvoyant controllers only); each day's
        draws come from (dataset, day label) alone."""
        missing = [c.label for c in ctxs if c.demand is None]
        if missing:
            raise ValueError(f"{self.name}: the day context of {missing} carries no true demand; the ceiling is "
                             f"clairvoyant and must be given it")
        c = ctxs[0]
        self.geom = c.geometry
        self.cells = torch.as_tensor(c.cells, dtype=torch.float32)
        self.params = ServiceParams.from_scenario(c.scenario)
        future = np.stack([np.asarray(d.demand, dtype=np.float32) for d in ctxs])
        self.future = torch.as_tensor(future.reshape(len(ctxs), future.shape[1], -1))  # (B, T, G)
        self.init = torch.as_tensor(np.stack([d.init_pos for d in ctxs]), dtype=torch.float32)  # (B, K, 2)
        self.rngs = [np.random.default_rng(int(stable_hash({"dataset": d.dataset, "day": str(d.label),
                                                            "method": "ceiling"}), 16)) for d in ctxs]
        self.chains: tuple[torch.Tensor, torch.Tensor] | None = None  # (B, C, K, 2) placements, (B, C, K) logits
        self.t = 0

    def fresh_starts(self, x: torch.Tensor, count: int) -> list[torch.Tensor]:
        """``count`` starts (B, K, 2) built from the map ``x`` (B, G) alone: its demand-weighted K-means from the
        initial deployment, then K-means from placements of K cells drawn in proportion to its demand."""
        starts = [lloyd(x, self.init, self.cells, LLOYD_ITERATIONS)][:count]
        if count > len(starts):
            cells = self.cells.numpy()
            drawn = np.stack([draw_placements(rng, x[i].numpy(), cells, self.init.shape[1], count - len(starts))
                              for i, rng in enumerate(self.rngs)])
            starts += [lloyd(x, d, self.cells, LLOYD_ITERATIONS)
                       for d in torch.as_tensor(drawn, dtype=torch.float32).unbind(1)]
        return starts

    def place_batch(self, obs: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray]:
        """The placement (B, K, 2) metres and bandwidth logits (B, K) for the next slot's TRUE map x_{t+1}: the best
        placement the search reaches from the chains (the best placements of the slot before; at slot 1 the initial
        deployment) and from the fresh starts of this slot's map, that best one then polished (``polish``)."""
        self.t += 1
        x = self.future[:, self.t]  # (B, G)
        b, k = self.init.shape[:2]
        if self.chains is None:
            self.chains = (self.init.unsqueeze(1), torch.zeros(b, 1, k))
        fresh = self.fresh_starts(x, self.options.fresh)
        starts = torch.cat([self.chains[0], *(f.unsqueeze(1) for f in fresh)], dim=1)
        logits = torch.cat([self.chains[1], torch.zeros(b, len(fresh), k)], dim=1)
        days = torch.arange(b).unsqueeze(1)
        with torch.no_grad():
            pos, logit, sr = ceiling_search(x, starts, logits, settings=self.options, cells=self.cells,
                                            geom=self.geom, params=self.params)
            if self.options.polish:  # the best placement searched again with finer rounds (it cannot serve less)
                top = sr.argmax(dim=1, keepdim=True)  # (B, 1): the first of equals
                fine = dataclasses.replace(self.options, refine=self.options.refine + self.options.polish)
                pos[days, top], logit[days, top], sr[days, top] = ceiling_search(
                    x, pos[days, top], logit[days, top], settings=fine, cells=self.cells, geom=self.geom,
                    params=self.params)
        # The `chains` best placements carry on to the next slot (a stable sort: ties to the earlier start).
        order = torch.sort(sr, dim=1, descending=True, stable=True).indices[:, : self.options.chains]
        self.chains = (pos[days, order], logit[days, order])
        return pos[days[:, 0], order[:, 0]].numpy(), logit[days[:, 0], order[:, 0]].numpy()

    def act_batch(self, obs: Mapping[str, Any]) -> np.ndarray:
        """The ceiling moves no fleet: the evaluation asks :meth:`place_batch` (its class says ``places``)."""
        raise NotImplementedError(f"method {self.name!r} is a per-slot bound: it places the fleet each slot "
                                  f"(place_batch), it has no action")
