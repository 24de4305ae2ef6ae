"""The one block-coordinate-descent (BCD) search of the project: Greedy, the oracle and DSWM's proposal call it.

Per slot, UAV by UAV, the best point of a displacement lattice around the UAV's position is chosen on a demand
map ``x`` with the other UAVs held at their current plan; ``refine`` rounds then score the 8 neighbours of the
best point at half the previous spacing; ``sweeps`` passes are made over the UAVs; in the last pass, when
``bw_logits`` is not empty, each UAV's bandwidth logit is searched over that set after its move. Each step scores
every (day, candidate) fleet with ONE call of ``dswm.sim.physics.served_ratio``. Where each UAV will be and
whether it can serve after the move comes from ``dswm.sim.fleet.fleet_step``, the function the environment steps
with, so a UAV that must return or that comes back from charging is planned exactly as it will move.

What differs between the callers is only the map they score on (the current observed map, the true next map, or
the world model's anchored imagined next map) and the :class:`SearchSettings` they pass.
"""
from __future__ import annotations

import dataclasses
import functools
from typing import Any, ClassVar, Mapping

import torch

from dswm.config import check_fields, setting, with_budget
from dswm.sim.fleet import ACTIVE, FleetState, Geometry, fleet_step
from dswm.sim.physics import DEMAND_EPS, ServiceParams, served_ratio
from dswm.sim.scenario import Scenario


@dataclasses.dataclass(frozen=True, kw_only=True)
class SearchSettings:
    """Strength of a BCD search (config.yaml ``search``, the one search every BCD of the project runs)."""

    sweeps: int = setting("count")
    """Passes over the UAVs per slot."""
    lattice: int = setting(schema={"type": "integer", "minimum": 3, "not": {"multipleOf": 2},
                                   "description": "an odd integer >= 3"})
    """Points per axis of the displacement lattice over [-D_max, D_max]^2."""
    refine: int = setting("natural")
    """Rounds of local refinement after the lattice, each at half the previous spacing."""
    bw_logits: tuple[float, ...] = setting(schema={
        "type": "array", "items": {"type": "number", "minimum": -1, "maximum": 1},
        "anyOf": [{"maxItems": 0}, {"contains": {"const": 0}}],
        "description": "[] (the demand-proportional split) or a list of bandwidth logits in [-1, 1] that includes 0"})
    """Bandwidth logits searched per UAV in the last sweep; () keeps the demand-proportional split (logit 0)."""

    section: ClassVar[str] = "search"
    """The config key of the section, for messages (one made in code; a built one names its own key)."""

    def __post_init__(self):
        check_fields(self, self.section)
        # 0 first, so a tie keeps the demand-proportional split.
        object.__setattr__(self, "bw_logits", tuple(sorted((float(v) for v in self.bw_logits), key=abs)))


def configured_search(config: Mapping[str, Any], profile: str) -> tuple[dict, str]:
    """config.yaml's ``search`` under ``profile``: the section with its ``search.budgets.<profile>`` entry merged in,
    and the key that names it in messages (``dswm.config.with_budget``). Every BCD of a run reads it here, so every
    method of a profile searches alike."""
    return with_budget(config["search"], profile, "search")


@functools.lru_cache(maxsize=16)
def lattice_offsets(points: int, d_max: float) -> torch.Tensor:
    """Displacements of a ``points x points`` lattice over [-D_max, D_max]^2 inside the D_max disk.

    Cached: every slot of a search asks for the same lattice, and no caller writes into it.

    Args:
        points: odd number of points per axis.
        d_max: largest displacement per slot, metres.

    Returns:
        (L, 2) float32 offsets in metres; row 0 is (0, 0), so ties keep a UAV where it is.
    """
    axis = torch.linspace(-d_max, d_max, points, dtype=torch.float64)
    grid = torch.stack(torch.meshgrid(axis, axis, indexing="ij"), dim=-1).reshape(-1, 2)
    grid = grid[torch.linalg.vector_norm(grid, dim=-1) <= d_max * (1 + 1e-9)]
    order = torch.argsort(torch.linalg.vector_norm(grid, dim=-1), stable=True)
    return grid[order].float()


_RING = torch.tensor([[-1, -1], [-1, 0], [-1, 1], [0, -1], [0, 1], [1, -1], [1, 0], [1, 1]], dtype=torch.float32)
"""The 8 lattice neighbours of a point (refinement rounds)."""


def _into_disk(points: torch.Tensor, centre: torch.Tensor, radius: float) -> torch.Tensor:
    """Project points (B, L, 2) onto the disk of ``radius`` around ``centre`` (B, 2): the reachable set."""
    d = points - centre.unsqueeze(1)
    norm = torch.linalg.vector_norm(d, dim=-1, keepdim=True)
    return centre.unsqueeze(1) + d * torch.clamp(radius / torch.clamp(norm, min=1e-9), max=1.0)


class _Rows:
    """Maps (B, G) and availability (B, K) repeated for n candidates per day, built once per slot and n."""

    def __init__(self, x: torch.Tensor, avail: torch.Tensor):
        self.x, self.avail, self.cache = x, avail, {}

    def get(self, n: int) -> tuple[torch.Tensor, torch.Tensor]:
        if n not in self.cache:
            self.cache[n] = (self.x.repeat_interleave(n, dim=0), self.avail.repeat_interleave(n, dim=0))
        return self.cache[n]


def to_action(target: torch.Tensor, pos: torch.Tensor, d_max: float) -> torch.Tensor:
    """(..., K, 2) displacement towards ``target`` as a fraction of D_max, norm-clipped to 1."""
    step = (target - pos) / d_max
    norm = torch.linalg.vector_norm(step, dim=-1, keepdim=True)
    return step / torch.clamp(norm, min=1.0)


def bcd_search(state: FleetState, x: torch.Tensor, *, search: SearchSettings, cells: torch.Tensor,
               geom: Geometry, scenario: Scenario, params: ServiceParams) -> tuple[torch.Tensor, torch.Tensor]:
    """Block-coordinate descent of one slot for B days.

    Args:
        state: the observed fleet state, leading shape (B,).
        x: (B, G) the demand map the plan is scored on.
        search: the search's strength.
        cells: (G, 2) cell centres in metres.
        geom, scenario, params: the area, the constants and the service parameters.

    Returns:
        Planned positions (B, K, 2) and bandwidth logits (B, K).
    """
    b, k = state.status.shape
    offsets = lattice_offsets(search.lattice, scenario.d_max_m)
    spacing = 2.0 * scenario.d_max_m / (search.lattice - 1)
    # Where each UAV is after this slot if it does not move, and whether it can serve then.
    nxt, _ = fleet_step(state, torch.zeros(b, k, 3), geom, scenario)
    avail = nxt.status == ACTIVE  # (B, K)
    movable = state.status == ACTIVE  # only active UAVs follow an action
    plan = nxt.pos.clone()  # (B, K, 2)
    logit = torch.zeros(b, k)
    # Cells without demand on every day of the batch change nothing: score on the others only.
    cols = (x > DEMAND_EPS).any(0).nonzero().squeeze(-1)
    if cols.numel() == 0:
        return plan, logit
    x, cells = x[:, cols], cells[cols]
    levels = torch.tensor(search.bw_logits, dtype=torch.float32)
    rows = _Rows(x, avail)  # per-candidate copies of the maps and availability, made once per slot
    with_logits = bool(search.bw_logits)

    def pick(j: int, cand: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Best of the candidate points ``cand`` (B, L, 2) of UAV j, the others at ``plan``; ties go to the first.
        One call of the physics scores all B*L candidate fleets. Returns (B, 2) the point and (B,) its score."""
        n_cand = cand.shape[1]
        fleets = plan.unsqueeze(1).expand(b, n_cand, k, 2).clone()  # (B, L, K, 2)
        fleets[:, :, j] = cand
        x_n, avail_n = rows.get(n_cand)
        sr = served_ratio(x_n, fleets.reshape(b * n_cand, k, 2), avail_n, cells, params=params,
                          bw_logit=logit.repeat_interleave(n_cand, dim=0) if with_logits else None)
        best_sr, idx = sr.reshape(b, n_cand).max(dim=1)
        return cand[torch.arange(b), idx], best_sr

    for sweep in range(search.sweeps):
        for j in range(k):
            take = movable[:, j] & avail[:, j]  # (B,) days on which UAV j can move and serve
            if not bool(take.any()):
                continue
            # Lattice of reachable points of UAV j, the others held at their plan; then finer rounds.
            home = state.pos[:, j]  # (B, 2)
            cand = geom.clip(home.unsqueeze(1) + offsets.unsqueeze(0))  # (B, L, 2)
            best, best_sr = pick(j, cand)
            for r in range(1, search.refine + 1):
                step = spacing / 2**r * _RING.unsqueeze(0)  # (1, 8, 2): the 8 neighbours
                cand = geom.clip(_into_disk(best.unsqueeze(1) + step, home, scenario.d_max_m))
                near, near_sr = pick(j, cand)
                better = near_sr > best_sr  # a neighbour must beat the point it surrounds
                best = torch.where(better.unsqueeze(-1), near, best)
                best_sr = torch.maximum(near_sr, best_sr)
            plan[:, j] = torch.where(take.unsqueeze(-1), best, plan[:, j])
            if with_logits and sweep == search.sweeps - 1:
                # Last sweep: then its bandwidth logit, positions fixed.
                lg = logit.unsqueeze(1).expand(b, len(levels), k).clone()
                lg[:, :, j] = levels.unsqueeze(0)
                x_n, avail_n = rows.get(len(levels))
                sr = served_ratio(x_n, plan.repeat_interleave(len(levels), dim=0), avail_n, cells,
                                  params=params, bw_logit=lg.reshape(-1, k)).reshape(b, len(levels))
                logit[:, j] = torch.where(take, levels[sr.argmax(dim=1)], logit[:, j])
    return plan, logit
