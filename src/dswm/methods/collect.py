"""Heuristic pre-collection of TRAINING-day transitions into a :class:`~dswm.methods.replay.SequenceReplay`.

Shared by the methods that start from pre-collected episodes (DSWM's world model, TD-MPC); each reads its own
:class:`CollectSettings` from its own config section (``dswm.training``, ``methods.tdmpc.precollect``). The heuristic
is a Lloyd step toward the demand centroid of each UAV's Voronoi region (:func:`lloyd_step`, also the continuation
of DSWM+'s imagined steps) or the greedy baseline with a cheap search, plus exploration noise.
"""
from __future__ import annotations

import dataclasses
import math
from typing import ClassVar, Literal

import numpy as np
import torch
from tqdm import tqdm

from dswm.config import ENUM, check_fields, setting
from dswm.methods.replay import SequenceReplay
from dswm.methods.search import SearchSettings
from dswm.sim.core import fleet_state_from_obs
from dswm.sim.fleet import available
from dswm.sim.physics import associate, sum_per_uav


@dataclasses.dataclass(frozen=True, kw_only=True)
class CollectSettings:
    """How episodes are pre-collected (values and reasons in config.yaml ``dswm.training``)."""

    collect_policy: Literal["lloyd", "greedy"] = setting(ENUM)
    """"lloyd" (move to the demand centroid of the UAV's Voronoi region) or "greedy" (dswm.methods.classical)."""
    collect_parallel: int = setting("count")
    """Training days stepped together during pre-collection."""
    explore_std: float = setting("nonnegative")
    """Std of the Gaussian noise added to the heuristic's moves (fraction of D_max)."""
    bw_explore_std: float = setting("nonnegative")
    """Std of the Gaussian bandwidth logits of the pre-collection policy."""
    collect_search: SearchSettings = setting(ref="search")
    """The search of ``collect_policy: greedy`` (a cheap one: pre-collection needs varied, sensible moves)."""

    section: ClassVar[str] = "collection settings"
    """The config key of the section, for messages (a subclass's own)."""

    def __post_init__(self):
        check_fields(self, self.section)


def lloyd_step(x: torch.Tensor, assoc: torch.Tensor, pos: torch.Tensor, cells: torch.Tensor,
               d_max: float) -> torch.Tensor:
    """Move of each UAV toward the demand-weighted centroid of the cells it serves (a Lloyd step).

    Args:
        x: (N, G) or (G,) demand; assoc: (N, G) serving UAV of each cell; pos: (N, K, 2) metres;
        cells: (G, 2); d_max: largest displacement per slot.
    Returns:
        (N, K, 2) displacement as a fraction of d_max, norm at most 1 (0 for a UAV that serves no demand).
    """
    n, k, _ = pos.shape
    x = x.expand(n, -1)
    # One scatter per quantity: a scatter with an expanded (N, G, 2) index is several times slower on CPU.
    mass = sum_per_uav(x, assoc, k)
    wsum = torch.stack([sum_per_uav(x * cells[:, 0], assoc, k), sum_per_uav(x * cells[:, 1], assoc, k)], -1)
    target = torch.where(mass.unsqueeze(-1) > 0, wsum / mass.clamp_min(1e-12).unsqueeze(-1), pos)
    move = (target - pos) / d_max
    return move / torch.linalg.vector_norm(move, dim=-1, keepdim=True).clamp_min(1.0)


def lloyd_moves(obs: dict, core, rng: np.random.Generator, cfg: CollectSettings) -> np.ndarray:
    """Heuristic action (B, K, 3): each UAV heads for the demand-weighted centroid of the cells it serves
    (:func:`lloyd_step`), plus exploration noise; bandwidth logits are drawn around 0."""
    state = fleet_state_from_obs(obs["fleet"], core.grid, core.scenario)
    x = torch.as_tensor(obs["demand"][:, -1]).reshape(len(state.pos), -1)     # (B, G)
    cells = core.cells.cpu().float()
    assoc = associate(state.pos, available(state), cells)                    # (B, G)
    move = lloyd_step(x, assoc, state.pos, cells, core.scenario.d_max_m)
    b, k = state.status.shape
    noise = rng.normal(0.0, cfg.explore_std, size=(b, k, 2))
    bw = rng.normal(0.0, cfg.bw_explore_std, size=(b, k, 1))
    return np.clip(np.concatenate([move.numpy() + noise, bw], -1), -1.0, 1.0).astype(np.float32)


def _greedy_policy(core, search: SearchSettings):
    """A batched greedy controller over the core's days (lazy import: baselines are optional here)."""
    from dswm.methods.base import DayContext
    from dswm.methods.classical import GreedyController

    greedy = GreedyController(name="greedy", options=search)

    def reset(rows):
        greedy.reset_batch([DayContext(dataset=core.dataset, day=int(r), label=core.day_labels[r], split="train",
                                       grid=core.grid, scenario=core.scenario, geometry=core.geom, cells=core.cells,
                                       init_pos=core.init_pos.cpu().numpy()) for r in rows])
    return greedy, reset


def collect(core, *, n_transitions: int, cfg: CollectSettings, seed: int, day_ids: np.ndarray) -> SequenceReplay:
    """Play heuristic episodes on the training-days core until ``n_transitions`` decisions are stored.

    Args:
        core: a ``FleetCore`` whose rows are TRAINING days only; day_ids: (D,) their tensor day indices.
        n_transitions: decisions to collect (rounded up to whole days); cfg: settings; seed: noise seed.
    Returns:
        The filled ``SequenceReplay`` (days visited round-robin, ``collect_parallel`` at a time).
    """
    s = core.scenario
    geom = core.geom
    replay = SequenceReplay(demand=core.demand.reshape(core.n_days, s.slots_per_day, core.grid.rows,
                                                       core.grid.cols).cpu().numpy(),
                            day_ids=day_ids, window=s.obs_window, width_m=geom.width_m, height_m=geom.height_m,
                            slots_per_day=s.slots_per_day)
    rng = np.random.default_rng(seed)
    n_dec = s.slots_per_day - 1
    n_episodes = max(1, math.ceil(n_transitions / n_dec))
    greedy = _greedy_policy(core, cfg.collect_search) if cfg.collect_policy == "greedy" else None
    bar = tqdm(total=n_episodes * n_dec, desc="collect", unit="tr", mininterval=5.0)
    done = 0
    while done < n_episodes:
        rows = [(done + j) % core.n_days for j in range(min(cfg.collect_parallel, n_episodes - done))]
        obs = core.reset(rows)
        if greedy is not None:
            greedy[1](rows)
        fleet, acts, srs = [obs["fleet"]], [], []
        for _ in range(n_dec):
            if greedy is None:
                a = lloyd_moves(obs, core, rng, cfg)
            else:
                a = greedy[0].act_batch(obs)
                a[..., :2] += rng.normal(0.0, cfg.explore_std, size=a[..., :2].shape)
                a[..., 2:] = rng.normal(0.0, cfg.bw_explore_std, size=a[..., 2:].shape)
                a = np.clip(a, -1.0, 1.0).astype(np.float32)
            out = core.step(a)
            obs = out.obs
            fleet.append(obs["fleet"])
            acts.append(a)
            srs.append(out.sr)
            bar.update(len(rows))
        fleet, acts, srs = np.stack(fleet, 1), np.stack(acts, 1), np.stack(srs, 1)
        for j, r in enumerate(rows):
            replay.add_episode(row=r, fleet=fleet[j], actions=acts[j], next_sr=srs[j])
        done += len(rows)
    bar.close()
    return replay
