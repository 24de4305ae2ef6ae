"""Episode replay of pre-collected TRAINING-day transitions, sampled as fixed-length sequences (DSWM's world model
trains on it; TD-MPC's ``TransitionReplay`` extends it with rewards).

Demand maps are not copied per step: the buffer holds the training demand tensor once and indexes it by
(day row, slot), building each observation window x_{t-w..t} with the environment's rule (edge-padded with the
day's first map before slot w). Per episode (one day, T decisions) it stores the observed fleet block
(T+1, K, 7), the actions (T, K, 3) and the realized next-slot served ratios (T,). Every episode records its
tensor day index, so the training manifest lists the day of every transition.
"""
from __future__ import annotations

import math

import numpy as np
import torch


class SequenceReplay:
    """Episodes of one dataset's training days."""

    def __init__(self, *, demand: np.ndarray, day_ids: np.ndarray, window: int, width_m: float,
                 height_m: float, slots_per_day: int):
        """Args:
            demand: (D, S, R, C) float32 training demand (rows of the environment core's tensor).
            day_ids: (D,) tensor day index of each row of ``demand``.
            window: w, the observation holds w+1 maps; width_m, height_m: area size (denormalizes positions).
            slots_per_day: S.
        """
        self.demand = torch.as_tensor(np.asarray(demand, dtype=np.float32))
        self.day_ids = np.asarray(day_ids, dtype=np.int64)
        self.window, self.slots = window, slots_per_day
        self.scale = torch.tensor([width_m, height_m], dtype=torch.float32)
        self.rows: list[int] = []             # row of ``demand`` of each episode
        self.fleet: list[torch.Tensor] = []   # (T+1, K, 7)
        self.actions: list[torch.Tensor] = []  # (T, K, 3)
        self.next_sr: list[torch.Tensor] = []  # (T,)

    def __len__(self) -> int:
        return len(self.rows)

    @property
    def n_transitions(self) -> int:
        return sum(a.shape[0] for a in self.actions)

    def episode_days(self) -> list[int]:
        """Tensor day index of every stored episode (each holds ``slots_per_day - 1`` transitions)."""
        return [int(self.day_ids[r]) for r in self.rows]

    def add_episode(self, *, row: int, fleet: np.ndarray, actions: np.ndarray, next_sr: np.ndarray) -> None:
        """Store one day.

        Args:
            row: row of ``demand`` the episode was played on; fleet: (T+1, K, 7) observed fleet blocks;
            actions: (T, K, 3) actions taken; next_sr: (T,) served ratio realized after each action.
        """
        t = actions.shape[0]
        if fleet.shape[0] != t + 1 or next_sr.shape != (t,):
            raise ValueError(f"SequenceReplay.add_episode: expected fleet (T+1, K, 7) and next_sr (T,) for "
                             f"T={t}, found {fleet.shape} and {next_sr.shape}")
        self.rows.append(int(row))
        self.fleet.append(torch.as_tensor(np.asarray(fleet, dtype=np.float32)))
        self.actions.append(torch.as_tensor(np.asarray(actions, dtype=np.float32)))
        self.next_sr.append(torch.as_tensor(np.asarray(next_sr, dtype=np.float32)))

    def window_maps(self, row: torch.Tensor, slot: torch.Tensor) -> torch.Tensor:
        """Observation windows x_{t-w..t} (edge-padded at the day's start): row, slot (...) -> (..., w+1, R, C)."""
        offs = torch.arange(-self.window, 1)
        idx = (slot.unsqueeze(-1) + offs).clamp_min(0)                   # (..., w+1)
        return self.demand[row.unsqueeze(-1).expand_as(idx), idx]

    def strip_maps(self, row: torch.Tensor, start: torch.Tensor, length: int,
                   maps: torch.Tensor | None = None) -> torch.Tensor:
        """The maps x_{s-w..s+length-1} that the windows of slots s..s+length-1 read, edge-padded as
        ``window_maps`` pads: row, start (B,) -> (B, length + w, R, C); window t of sequence b is
        ``strip[b, t:t + w + 1]``. Read from ``maps`` (a transform of ``demand``) when given."""
        idx = (start.unsqueeze(-1) + torch.arange(-self.window, length)).clamp_min(0)   # (B, length + w)
        return (self.demand if maps is None else maps)[row.unsqueeze(-1).expand_as(idx), idx]

    def time_features(self, slot: torch.Tensor) -> torch.Tensor:
        """[sin, cos] of 2 pi slot / S, (...) -> (..., 2)."""
        ang = 2.0 * math.pi * slot.to(torch.float32) / self.slots
        return torch.stack([torch.sin(ang), torch.cos(ang)], -1)

    def sample(self, batch: int, seq_len: int, generator: torch.Generator) -> dict[str, torch.Tensor]:
        """Sample ``batch`` windows of ``seq_len`` consecutive decisions.

        Returns:
            dict with ``demand`` (L, B, w+1, R, C), ``fleet`` (L, B, K, 7), ``time`` (L, B, 2), ``prev_action``
            and ``action`` (L, B, K, 3), ``next_demand`` (L, B, R, C), ``next_pos`` (L, B, K, 2) metres,
            ``next_avail`` (L, B, K) bool, ``next_sr`` (L, B), ``day`` (B,) tensor day indices.
        """
        if not self.rows:
            raise ValueError("SequenceReplay.sample: the buffer is empty")
        eps = torch.randint(len(self.rows), (batch,), generator=generator)
        out = {k: [] for k in ("fleet", "prev_action", "action", "next_fleet", "next_sr", "slot", "row")}
        for e in eps.tolist():
            n_dec = self.actions[e].shape[0]
            if n_dec < seq_len:
                raise ValueError(f"SequenceReplay.sample: seq_len {seq_len} exceeds the episode length {n_dec}")
            s = int(torch.randint(n_dec - seq_len + 1, (1,), generator=generator))
            sl = slice(s, s + seq_len)
            acts = self.actions[e]
            prev = torch.cat([acts[s - 1:s] if s > 0 else torch.zeros_like(acts[:1]), acts[s:s + seq_len - 1]])
            out["fleet"].append(self.fleet[e][sl])
            out["next_fleet"].append(self.fleet[e][s + 1:s + seq_len + 1])
            out["action"].append(acts[sl])
            out["prev_action"].append(prev)
            out["next_sr"].append(self.next_sr[e][sl])
            out["slot"].append(torch.arange(s, s + seq_len))
            out["row"].append(torch.full((seq_len,), self.rows[e]))
        st = {k: torch.stack(v, 1) for k, v in out.items()}              # (L, B, ...)
        nxt = st.pop("next_fleet")
        return {
            "demand": self.window_maps(st["row"], st["slot"]),
            "fleet": st["fleet"], "time": self.time_features(st["slot"]),
            "prev_action": st["prev_action"], "action": st["action"],
            "next_demand": self.demand[st["row"], st["slot"] + 1],
            "next_pos": nxt[..., :2] * self.scale, "next_avail": nxt[..., 3] > 0.5,
            "next_sr": st["next_sr"], "day": torch.as_tensor(self.day_ids[st["row"][0].numpy()]),
        }

    def state_dict(self) -> dict:
        """Everything needed to rebuild the buffer (the demand tensor included, for a self-contained resume)."""
        return {"demand": self.demand, "day_ids": self.day_ids, "window": self.window, "slots": self.slots,
                "scale": self.scale, "rows": list(self.rows), "fleet": self.fleet, "actions": self.actions,
                "next_sr": self.next_sr}

    @classmethod
    def from_state_dict(cls, sd: dict) -> "SequenceReplay":
        rep = cls(demand=sd["demand"].numpy(), day_ids=sd["day_ids"], window=sd["window"],
                  width_m=float(sd["scale"][0]), height_m=float(sd["scale"][1]), slots_per_day=sd["slots"])
        rep.rows, rep.fleet, rep.actions, rep.next_sr = list(sd["rows"]), sd["fleet"], sd["actions"], sd["next_sr"]
        return rep
