"""Static, greedy and oracle controllers (SPEC section 5).

* static: the K-means positions of the initial deployment, held all day; a UAV that comes back from a
  station flies back to its spot.
* greedy (per-slot block-coordinate descent): each slot, UAV by UAV, the best point of a displacement
  lattice for the CURRENT observed map x_t, the others held at their current plan; ``sweeps`` passes;
  demand-proportional bandwidth (logit 0).
* oracle (clairvoyant upper bound): the same search, stronger (more sweeps, a finer lattice, the bandwidth
  logit of each UAV searched too), scored on the TRUE next-slot map x_{t+1}, which is what will be served.

All three are batched: the evaluated days of a job are stepped together, and each BCD step scores every
(day, lattice point) candidate fleet with ONE call of ``dswm.physics.served_ratio``. Where each UAV will be
and whether it can serve after the move comes from ``dswm.fleet.fleet_step`` of the observed fleet state,
the same function the environment steps with, so a UAV that must return or that comes back from charging
is planned exactly as the environment will move it.
"""
from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np
import torch

from dswm.controllers import Controller, DayContext
from dswm.core import fleet_state_from_obs
from dswm.fleet import ACTIVE, FleetState, fleet_step
from dswm.physics import DEMAND_EPS, ServiceParams, served_ratio


class BatchedController(Controller):
    """A controller whose single-day ``reset``/``act`` are the batched ones with B = 1."""

    batched = True

    def reset(self, ctx: DayContext) -> None:
        self.reset_batch([ctx])

    def act(self, obs: Mapping[str, Any]) -> np.ndarray:
        return self.act_batch({k: np.asarray(v)[None] for k, v in obs.items()})[0]

    def save(self, path) -> None:
        """Nothing to save: these methods have no learned state."""

    def load(self, path) -> None:
        """Nothing to load."""


def _to_action(target: torch.Tensor, pos: torch.Tensor, d_max: float) -> torch.Tensor:
    """(..., K, 2) displacement towards ``target`` as a fraction of D_max, norm-clipped to 1."""
    step = (target - pos) / d_max
    norm = torch.linalg.vector_norm(step, dim=-1, keepdim=True)
    return step / torch.clamp(norm, min=1.0)


class StaticController(BatchedController):
    """Hold the K-means deployment all day; bandwidth split proportional to demand."""

    deterministic = True

    def reset_batch(self, ctxs: Sequence[DayContext]) -> None:
        """Keep every day's initial positions (K, 2) as the targets."""
        self.ctx = ctxs[0]
        self.target = torch.as_tensor(np.stack([c.init_pos for c in ctxs]), dtype=torch.float32)  # (B, K, 2)

    def act_batch(self, obs: Mapping[str, Any]) -> np.ndarray:
        """(B, K, 3): fly towards the K-means spot (at most D_max per slot), bandwidth logit 0."""
        state = fleet_state_from_obs(obs["fleet"], self.ctx.grid, self.ctx.scenario)
        move = _to_action(self.target, state.pos, self.ctx.scenario.d_max_m)
        return torch.cat([move, torch.zeros_like(move[..., :1])], dim=-1).numpy()


def lattice_offsets(points: int, d_max: float) -> torch.Tensor:
    """Displacements of a ``points x points`` lattice over [-D_max, D_max]^2 inside the D_max disk.

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


class GreedyController(BatchedController):
    """Per-slot block-coordinate descent on the current observed map (SPEC section 5).

    Args:
        name, seed, device: see Controller.
        sweeps: passes over the UAVs per slot.
        lattice: points per axis of the displacement lattice.
        refine: rounds of local refinement after the lattice (0 for greedy): each scores the 8 neighbours of
            the best point at half the previous spacing, so the resolution is spacing / 2^refine.
    """

    deterministic = True

    def __init__(self, *, name: str, seed: int = 0, device: str = "cpu", sweeps: int, lattice: int,
                 refine: int = 0):
        super().__init__(name=name, seed=seed, device=device)
        if sweeps < 1 or lattice < 3 or lattice % 2 == 0 or refine < 0:
            raise ValueError(f"{name}: expected sweeps >= 1, an odd lattice >= 3 and refine >= 0, found "
                             f"{sweeps}, {lattice}, {refine}")
        self.sweeps, self.lattice, self.refine = sweeps, lattice, refine
        self.bw_logits: tuple[float, ...] = ()

    def reset_batch(self, ctxs: Sequence[DayContext]) -> None:
        """Keep the geometry and constants of the batch; the slot counter starts at 0."""
        c = ctxs[0]
        self.ctxs, self.grid, self.scenario, self.geom = list(ctxs), c.grid, c.scenario, c.geometry
        self.cells = torch.as_tensor(c.cells, dtype=torch.float32)
        self.params = ServiceParams.from_scenario(c.scenario)
        self.offsets = lattice_offsets(self.lattice, c.scenario.d_max_m)
        self.spacing = 2.0 * c.scenario.d_max_m / (self.lattice - 1)
        self.t = 0

    def target_demand(self, obs: Mapping[str, Any]) -> torch.Tensor:
        """(B, G) the map the plan is scored on: the current observed map x_t."""
        demand = torch.as_tensor(np.asarray(obs["demand"]))
        return demand[:, -1].reshape(demand.shape[0], -1).float()

    def act_batch(self, obs: Mapping[str, Any]) -> np.ndarray:
        """(B, K, 3) actions of one slot for B days."""
        x = self.target_demand(obs)
        self.t += 1
        state = fleet_state_from_obs(obs["fleet"], self.grid, self.scenario)
        with torch.no_grad():
            plan, logit = self._search(state, x)
        move = _to_action(plan, state.pos, self.scenario.d_max_m)
        return torch.cat([move, logit.unsqueeze(-1)], dim=-1).numpy()

    def _search(self, state: FleetState, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Block-coordinate descent; returns planned positions (B, K, 2) and bandwidth logits (B, K)."""
        b, k = state.status.shape
        # Where each UAV is after this slot if it does not move, and whether it can serve then.
        nxt, _ = fleet_step(state, torch.zeros(b, k, 3), self.geom, self.scenario)
        avail = nxt.status == ACTIVE  # (B, K)
        movable = state.status == ACTIVE  # only active UAVs follow an action
        plan = nxt.pos.clone()  # (B, K, 2)
        logit = torch.zeros(b, k)
        # Cells without demand on every day of the batch change nothing: score on the others only.
        cols = (x > DEMAND_EPS).any(0).nonzero().squeeze(-1)
        if cols.numel() == 0:
            return plan, logit
        x, cells = x[:, cols], self.cells[cols]
        levels = torch.tensor(self.bw_logits, dtype=torch.float32)
        rows = _Rows(x, avail)  # per-candidate copies of the maps and availability, made once per slot
        for sweep in range(self.sweeps):
            for j in range(k):
                take = movable[:, j] & avail[:, j]  # (B,) days on which UAV j can move and serve
                if not bool(take.any()):
                    continue
                # Lattice of reachable points of UAV j, the others held at their plan; then finer rounds.
                home = state.pos[:, j]  # (B, 2)
                cand = self.geom.clip(home.unsqueeze(1) + self.offsets.unsqueeze(0))  # (B, L, 2)
                best, best_sr = self._pick(rows, plan, logit, j, cand, cells)
                for r in range(1, self.refine + 1):
                    step = self.spacing / 2**r * _RING.unsqueeze(0)  # (1, 8, 2): the 8 neighbours
                    cand = self.geom.clip(_into_disk(best.unsqueeze(1) + step, home, self.scenario.d_max_m))
                    near, near_sr = self._pick(rows, plan, logit, j, cand, cells)
                    better = near_sr > best_sr  # a neighbour must beat the point it surrounds
                    best = torch.where(better.unsqueeze(-1), near, best)
                    best_sr = torch.maximum(near_sr, best_sr)
                plan[:, j] = torch.where(take.unsqueeze(-1), best, plan[:, j])
                if levels.numel() and sweep == self.sweeps - 1:
                    # Last sweep: then its bandwidth logit, positions fixed.
                    lg = logit.unsqueeze(1).expand(b, len(levels), k).clone()
                    lg[:, :, j] = levels.unsqueeze(0)
                    x_n, avail_n = rows.get(len(levels))
                    sr = served_ratio(x_n, plan.repeat_interleave(len(levels), dim=0), avail_n, cells,
                                      params=self.params, bw_logit=lg.reshape(-1, k)).reshape(b, len(levels))
                    logit[:, j] = torch.where(take, levels[sr.argmax(dim=1)], logit[:, j])
        return plan, logit

    def _pick(self, rows, plan, logit, j, cand, cells) -> tuple[torch.Tensor, torch.Tensor]:
        """Best of the candidate points ``cand`` (B, L, 2) of UAV j, the others at ``plan``.

        One call of the physics scores all B*L candidate fleets; ties go to the first candidate.

        Returns:
            (B, 2) best point and (B,) its served ratio.
        """
        b, n_cand = cand.shape[:2]
        k = plan.shape[1]
        fleets = plan.unsqueeze(1).expand(b, n_cand, k, 2).clone()  # (B, L, K, 2)
        fleets[:, :, j] = cand
        x_n, avail_n = rows.get(n_cand)
        sr = served_ratio(x_n, fleets.reshape(b * n_cand, k, 2), avail_n, cells, params=self.params,
                          bw_logit=logit.repeat_interleave(n_cand, dim=0) if self.bw_logits else None)
        best_sr, idx = sr.reshape(b, n_cand).max(dim=1)
        return cand[torch.arange(b), idx], best_sr


class _Rows:
    """Maps (B, G) and availability (B, K) repeated for n candidates per day, built once per slot and n."""

    def __init__(self, x: torch.Tensor, avail: torch.Tensor):
        self.x, self.avail, self.cache = x, avail, {}

    def get(self, n: int) -> tuple[torch.Tensor, torch.Tensor]:
        if n not in self.cache:
            self.cache[n] = (self.x.repeat_interleave(n, dim=0), self.avail.repeat_interleave(n, dim=0))
        return self.cache[n]


_RING = torch.tensor([[-1, -1], [-1, 0], [-1, 1], [0, -1], [0, 1], [1, -1], [1, 0], [1, 1]], dtype=torch.float32)
"""The 8 lattice neighbours of a point (refinement rounds)."""


def _into_disk(points: torch.Tensor, centre: torch.Tensor, radius: float) -> torch.Tensor:
    """Project points (B, L, 2) onto the disk of ``radius`` around ``centre`` (B, 2): the reachable set."""
    d = points - centre.unsqueeze(1)
    norm = torch.linalg.vector_norm(d, dim=-1, keepdim=True)
    return centre.unsqueeze(1) + d * torch.clamp(radius / torch.clamp(norm, min=1e-9), max=1.0)


class OracleController(GreedyController):
    """Clairvoyant upper bound: greedy's search, stronger, on the TRUE next-slot map (SPEC section 5).

    Args:
        name, seed, device, sweeps, lattice, refine: see GreedyController.
        bw_logits: bandwidth logits searched for each UAV after its position (must include 0).
    """

    clairvoyant = True

    def __init__(self, *, name: str, seed: int = 0, device: str = "cpu", sweeps: int, lattice: int,
                 refine: int, bw_logits: Sequence[float]):
        super().__init__(name=name, seed=seed, device=device, sweeps=sweeps, lattice=lattice, refine=refine)
        if 0.0 not in [float(v) for v in bw_logits] or any(abs(float(v)) > 1 for v in bw_logits):
            raise ValueError(f"{name}: bw_logits must lie in [-1, 1] and include 0, found {list(bw_logits)}")
        # 0 first, so a tie keeps the demand-proportional split.
        self.bw_logits = tuple(sorted((float(v) for v in bw_logits), key=abs))

    def reset_batch(self, ctxs: Sequence[DayContext]) -> None:
        """Take each day's true demand (T, R, C) from the context (handed to clairvoyant controllers only)."""
        missing = [c.label for c in ctxs if c.demand is None]
        if missing:
            raise ValueError(f"{self.name}: the day context of {missing} carries no true demand; the oracle is "
                             f"clairvoyant and must be given it")
        super().reset_batch(ctxs)
        self.future = torch.as_tensor(np.stack([np.asarray(c.demand, dtype=np.float32) for c in ctxs]))
        self.future = self.future.reshape(len(ctxs), self.future.shape[1], -1)  # (B, T, G)

    def target_demand(self, obs: Mapping[str, Any]) -> torch.Tensor:
        """(B, G) the TRUE map x_{t+1} that the planned fleet will serve."""
        return self.future[:, self.t + 1]
