"""Static, greedy and oracle controllers (docs/PROTOCOL.md §5).

* static: the K-means positions of the initial deployment, held all day; a UAV that comes back from a
  station flies back to its spot.
* greedy: the block-coordinate-descent search (``dswm.methods.search``) on the CURRENT observed map x_t.
* oracle (clairvoyant upper bound): the same search on the TRUE next-slot map x_{t+1}, which is what will be
  served.

All three are batched: the evaluated days of a job are stepped together. Greedy's and the oracle's strength is
the project's one :class:`~dswm.methods.search.SearchSettings` (config.yaml ``search``), shared by every BCD.
"""
from __future__ import annotations

from typing import Any, ClassVar, Mapping, Sequence

import numpy as np
import torch

from dswm.methods.base import Controller, DayContext
from dswm.methods.search import SearchSettings, bcd_search, configured_search, to_action
from dswm.sim.core import fleet_state_from_obs
from dswm.sim.physics import ServiceParams


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
        move = to_action(self.target, state.pos, self.ctx.scenario.d_max_m)
        return torch.cat([move, torch.zeros_like(move[..., :1])], dim=-1).numpy()


class GreedyController(BatchedController):
    """Per-slot block-coordinate descent on the current observed map (docs/PROTOCOL.md §5).

    Args:
        name, seed, device: see Controller.
        options: the search's strength.
    """

    deterministic = True
    options_type: ClassVar[type] = SearchSettings

    def __init__(self, *, name: str, seed: int = 0, device: str = "cpu", options: SearchSettings):
        super().__init__(name=name, seed=seed, device=device, options=options)

    @classmethod
    def options_from_config(cls, *, name: str, config: Mapping[str, Any], profile: str) -> SearchSettings:
        """The project's one search (config.yaml ``search``, with its budget for ``profile``): every BCD of a run
        searches alike."""
        section, key = configured_search(config, profile)
        return cls.options_from_plain(name=name, data=section, where=key)

    @property
    def search(self) -> SearchSettings:
        """The search's strength (its ``options``)."""
        return self.options

    def search_settings(self) -> SearchSettings:
        """Its BCD search (the shared ``search`` section)."""
        return self.options

    def reset_batch(self, ctxs: Sequence[DayContext]) -> None:
        """Keep the geometry and constants of the batch; the slot counter starts at 0."""
        c = ctxs[0]
        self.ctxs, self.grid, self.scenario, self.geom = list(ctxs), c.grid, c.scenario, c.geometry
        self.cells = torch.as_tensor(c.cells, dtype=torch.float32)
        self.params = ServiceParams.from_scenario(c.scenario)
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
            plan, logit = bcd_search(state, x, search=self.search, cells=self.cells, geom=self.geom,
                                     scenario=self.scenario, params=self.params)
        move = to_action(plan, state.pos, self.scenario.d_max_m)
        return torch.cat([move, logit.unsqueeze(-1)], dim=-1).numpy()


class OracleController(GreedyController):
    """Clairvoyant upper bound: the BCD search on the TRUE next-slot map (docs/PROTOCOL.md §5).

    Args:
        name, seed, device, options: see GreedyController (the shared search).
    """

    clairvoyant = True


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
