"""MADDPG's replay buffer: joint transitions of the fleet, demand kept by reference.

The demand part of an observation is the window x_{t-w..t} of one training day (edge-padded with the day's
first map), so a transition stores (day, slot) and :func:`window_maps` reads the maps back from the training
tensor; fleet features, time phase, joint action, team reward and the two end flags are stored as given. At
K = 16 a transition takes ~1.1 kB instead of ~22 kB with its two 20 x 20 x 7 windows.
"""
from __future__ import annotations

import torch

from dswm.methods.maddpg.networks import N_ACTION, N_FLEET

FIELDS = ("day", "slot", "fleet", "time", "action", "reward", "terminated", "truncated", "next_fleet", "next_time")


def window_maps(days: torch.Tensor, day: torch.Tensor, slot: torch.Tensor, maps: int) -> torch.Tensor:
    """(N, maps, R, C) the observed windows x_{t-maps+1..t} of (day, slot) pairs, edge-padded at the day's start.

    Args:
        days: (D, T, R, C) the training days' maps (demand, or demand scaled); day, slot: (N,) int64.
    """
    idx = torch.clamp(slot.unsqueeze(1) + torch.arange(1 - maps, 1, device=slot.device), min=0)
    return days[day.unsqueeze(1), idx]


class Replay:
    """A ring buffer of ``capacity`` joint transitions of ``n_agents`` UAVs (the oldest overwritten first)."""

    def __init__(self, *, capacity: int, n_agents: int):
        self.capacity, self.n_agents = capacity, n_agents
        k = n_agents
        shapes = {"day": ((), torch.long), "slot": ((), torch.long), "fleet": ((k, N_FLEET), torch.float32),
                  "time": ((2,), torch.float32), "action": ((k, N_ACTION), torch.float32),
                  "reward": ((), torch.float32), "terminated": ((), torch.bool), "truncated": ((), torch.bool),
                  "next_fleet": ((k, N_FLEET), torch.float32), "next_time": ((2,), torch.float32)}
        # torch.empty: a large buffer's pages are committed only as transitions fill them
        self.data = {name: torch.empty((capacity, *shape), dtype=dtype) for name, (shape, dtype) in shapes.items()}
        self.size = 0
        self.pos = 0

    def __len__(self) -> int:
        return self.size

    def add(self, **transition) -> None:
        """Store one transition: every name of :data:`FIELDS`, shapes as in the buffer without the leading axis."""
        if set(transition) != set(FIELDS):
            raise ValueError(f"Replay.add: expected the fields {list(FIELDS)}, found {sorted(transition)}")
        for name, value in transition.items():
            self.data[name][self.pos] = torch.as_tensor(value)
        self.pos = (self.pos + 1) % self.capacity
        self.size = min(self.size + 1, self.capacity)

    def sample(self, n: int, generator: torch.Generator) -> dict[str, torch.Tensor]:
        """``n`` transitions drawn uniformly with replacement (indices from ``generator``)."""
        if self.size == 0:
            raise RuntimeError("Replay.sample: the buffer is empty")
        idx = torch.randint(0, self.size, (n,), generator=generator)
        return self.take(idx)

    def take(self, idx: torch.Tensor) -> dict[str, torch.Tensor]:
        """The transitions at buffer rows ``idx``."""
        return {name: value[idx] for name, value in self.data.items()}

    def state_dict(self) -> dict:
        """The filled rows and the write position."""
        return {"size": self.size, "pos": self.pos, "capacity": self.capacity,
                "data": {name: value[: self.size].clone() for name, value in self.data.items()}}

    def load_state_dict(self, state: dict) -> None:
        if state["capacity"] != self.capacity or state["data"]["fleet"].shape[1] != self.n_agents:
            raise ValueError(f"replay state of capacity {state['capacity']} and "
                             f"{state['data']['fleet'].shape[1]} agents; expected {self.capacity} and {self.n_agents}")
        self.size, self.pos = int(state["size"]), int(state["pos"])
        for name, value in state["data"].items():
            self.data[name][: self.size] = value
