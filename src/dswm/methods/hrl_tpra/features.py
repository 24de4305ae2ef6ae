"""What each level of HRL-TPRA sees, and how a resource actor's output becomes the environment's action.

Observations are the environment's (``dswm.sim.core.build_observation``) as float32 tensors: demand (B, w+1, R, C),
fleet (B, K, 7), time (B, 2). Demand enters every network through the fixed log1p (nothing fitted on any day).

* The planner (high level, :func:`plan_inputs`): the top-N cells of the CURRENT observed map x_t, each with
  :data:`CAND_FEATURES`; every UAV's fleet features; the (K, N) UAV-to-candidate distances in units of D_max; and
  a flat summary (candidates, fleet, time, mean demand) for its value network.
* A resource actor (low level, :func:`low_inputs`): its own fleet features; the offset to its target cell in units
  of D_max, the distance and the target's demand; the (2 r + 1)^2 crop of log1p x_t around its own cell and the
  count of the OTHER active UAVs in each cell of the crop (zero outside the area); the time phase and the share of
  the macro-slot elapsed. Its critic also sees :data:`GLOBAL_FEATURES` of the fleet's state.
* The action (:func:`compose_action`): (dx, dy) = the move toward the target (norm at most 1, i.e. at most D_max)
  plus ``fine_scale`` times the actor's fine move, clipped to [-1, 1]; the bandwidth logit is the actor's third
  output. The environment clips the displacement's norm to D_max.
"""
from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import torch
from torch.nn import functional as F

CAND_FEATURES = ("x_over_width", "y_over_height", "log1p_now", "log1p_window_mean", "log1p_trend",
                 "nearest_active_uav_over_dmax")
"""Features of a candidate cell (the planner's encoder input)."""
GLOBAL_FEATURES = ("mean_log1p_now", "active_fraction")
"""Fleet-wide features appended to each resource critic's input."""
FAR = 4.0
"""Distances in units of D_max are capped here (a candidate no active UAV is near)."""
N_FLEET = 7
N_ACTION = 3


@dataclasses.dataclass(frozen=True)
class Frame:
    """Geometry a level needs: cell centres (G, 2) in metres, the area, the grid's shape and D_max."""

    cells: torch.Tensor
    width_m: float
    height_m: float
    rows: int
    cols: int
    d_max_m: float

    @classmethod
    def of(cls, grid, scenario, device: str | torch.device = "cpu") -> "Frame":
        geom = grid.geometry()
        return cls(cells=grid.cells(device=device), width_m=geom.width_m, height_m=geom.height_m, rows=grid.rows,
                   cols=grid.cols, d_max_m=float(scenario.d_max_m))

    def positions(self, fleet: torch.Tensor) -> torch.Tensor:
        """(..., K, 2) positions in metres from the fleet features x / W and y / H."""
        return torch.stack([fleet[..., 0] * self.width_m, fleet[..., 1] * self.height_m], dim=-1)

    def cell_of(self, fleet: torch.Tensor) -> torch.Tensor:
        """(..., K) flattened cell index (row * cols + col, row 0 south) of each UAV."""
        col = torch.clamp((fleet[..., 0] * self.cols).floor().long(), 0, self.cols - 1)
        row = torch.clamp((fleet[..., 1] * self.rows).floor().long(), 0, self.rows - 1)
        return row * self.cols + col


def local_dim(radius: int) -> int:
    """Width of a resource actor's input: fleet (7), offset (2), distance, target demand, two crops, time (2),
    macro phase."""
    side = 2 * radius + 1
    return N_FLEET + 2 + 1 + 1 + 2 * side * side + 2 + 1


def summary_dim(candidates: int, n_uavs: int) -> int:
    """Width of the planner value network's input."""
    return candidates * len(CAND_FEATURES) + n_uavs * N_FLEET + 2 + 1


class PlanInputs(NamedTuple):
    """The planner's view of B observations."""

    cells: torch.Tensor
    """(B, N) int64 flattened index of each candidate cell (top-N of x_t, largest first)."""
    cand: torch.Tensor
    """(B, N, len(CAND_FEATURES)) candidate features."""
    uav: torch.Tensor
    """(B, K, 7) fleet features, the decoder's input at UAV k's step."""
    dist: torch.Tensor
    """(B, K, N) distance of UAV k to candidate j over D_max, capped at FAR."""
    summary: torch.Tensor
    """(B, summary_dim) the value network's input."""


def plan_inputs(demand: torch.Tensor, fleet: torch.Tensor, time: torch.Tensor, frame: Frame,
                candidates: int) -> PlanInputs:
    """The planner's inputs from a batch of observations (see :class:`PlanInputs`)."""
    b = demand.shape[0]
    maps = torch.log1p(demand.reshape(b, demand.shape[1], -1))  # (B, w+1, G)
    now = maps[:, -1]
    _, cells = torch.topk(now, candidates, dim=1, sorted=True)  # (B, N)
    centre = frame.cells[cells]  # (B, N, 2)
    pos = frame.positions(fleet)  # (B, K, 2)
    dist = (torch.cdist(pos, centre) / frame.d_max_m).clamp(max=FAR)  # (B, K, N)
    active = fleet[..., 3] > 0.5
    nearest = torch.where(active.unsqueeze(-1), dist, torch.full_like(dist, FAR)).min(dim=1).values  # (B, N)
    cand = torch.stack([centre[..., 0] / frame.width_m, centre[..., 1] / frame.height_m, now.gather(1, cells),
                        maps.mean(1).gather(1, cells), now.gather(1, cells) - maps[:, 0].gather(1, cells),
                        nearest], dim=-1)
    summary = torch.cat([cand.reshape(b, -1), fleet.reshape(b, -1), time, now.mean(1, keepdim=True)], dim=-1)
    return PlanInputs(cells=cells, cand=cand, uav=fleet, dist=dist, summary=summary)


def low_inputs(demand: torch.Tensor, fleet: torch.Tensor, time: torch.Tensor, target: torch.Tensor,
               phase: torch.Tensor, frame: Frame, radius: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The resource actors' inputs.

    Args:
        demand: (B, w+1, R, C); fleet: (B, K, 7); time: (B, 2).
        target: (B, K) int64 target cell of each UAV (from the planner).
        phase: (B,) share of the macro-slot elapsed, in [0, 1).
        frame: geometry; radius: crop half-width r in cells.

    Returns:
        local (B, K, local_dim(r)) and glob (B, len(GLOBAL_FEATURES)).
    """
    b, k = fleet.shape[:2]
    side = 2 * radius + 1
    now = torch.log1p(demand[:, -1])  # (B, R, C)
    flat = now.reshape(b, -1)
    active = (fleet[..., 3] > 0.5).to(now.dtype)
    own = frame.cell_of(fleet)  # (B, K)
    occupancy = torch.zeros_like(flat).scatter_add_(1, own, active)
    channels = torch.stack([now, occupancy.view_as(now)], dim=1)  # (B, 2, R, C)
    patches = F.unfold(F.pad(channels, (radius,) * 4), kernel_size=side)  # (B, 2 S S, G), (channel, row, col) order
    crop = patches.gather(2, own.unsqueeze(1).expand(b, patches.shape[1], k)).transpose(1, 2).clone()  # (B, K, 2SS)
    crop[..., side * side + radius * side + radius] -= active  # a UAV does not count itself
    offset = (frame.cells[target] - frame.positions(fleet)) / frame.d_max_m  # (B, K, 2)
    local = torch.cat([fleet, offset, offset.norm(dim=-1, keepdim=True), flat.gather(1, target).unsqueeze(-1), crop,
                       time.unsqueeze(1).expand(b, k, 2), phase.view(b, 1, 1).expand(b, k, 1)], dim=-1)
    glob = torch.stack([flat.mean(1), active.mean(1)], dim=-1)
    return local, glob


def compose_action(out: torch.Tensor, fleet: torch.Tensor, target: torch.Tensor, frame: Frame,
                   fine_scale: float) -> torch.Tensor:
    """The environment's action (B, K, 3) in [-1, 1] from the actors' outputs ``out`` (B, K, 3) in [-1, 1].

    (dx, dy) = clip(toward + fine_scale * out[..., :2], -1, 1), toward the target cell's centre in units of D_max
    with its norm capped at 1 (the target is reached in one slot when it lies within D_max); the bandwidth logit
    is out[..., 2].
    """
    toward = (frame.cells[target] - frame.positions(fleet)) / frame.d_max_m
    norm = toward.norm(dim=-1, keepdim=True)
    toward = toward * torch.clamp(1.0 / norm.clamp(min=1e-9), max=1.0)
    move = (toward + fine_scale * out[..., :2]).clamp(-1.0, 1.0)
    return torch.cat([move, out[..., 2:].clamp(-1.0, 1.0)], dim=-1)


def slot_of(time: torch.Tensor, slots_per_day: int) -> torch.Tensor:
    """(B,) int64 slot index t recovered from the time phase (sin, cos of 2 pi t / T)."""
    phase = torch.atan2(time[:, 0].double(), time[:, 1].double()) % (2 * math.pi)
    return torch.round(phase / (2 * math.pi) * slots_per_day).long() % slots_per_day
