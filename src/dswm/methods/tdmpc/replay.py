"""TD-MPC's replay: the shared episode replay (``dswm.methods.replay.SequenceReplay``) plus each transition's reward and termination flag,
sampled as windows of H+1 consecutive observations of one day.

The pre-collection stores fleets, actions and served ratios but not rewards; the reward of each of its
transitions is recomputed exactly as the environment computes it (paper eq. 7, :func:`episode_rewards`): the
fleet energy of the slot from ``dswm.sim.fleet.fleet_step`` on the recorded state and action, the served ratio as
recorded. A day's last transition is TRUNCATED, never terminated (``FleetCore.step``): its flag is False and its
TD target bootstraps on the day's final observation, which the replay keeps (fleet block T, demand window of
slot T).
"""
from __future__ import annotations

import numpy as np
import torch

from dswm.methods.replay import SequenceReplay
from dswm.methods.tdmpc.model import scale_demand
from dswm.sim.core import fleet_state_from_obs
from dswm.sim.energy import hover_power
from dswm.sim.fleet import fleet_step


def step_reward(sr: torch.Tensor, energy_j: torch.Tensor, scenario) -> torch.Tensor:
    """Paper eq. 7 as ``FleetCore.step`` computes it: SR - beta (1 - SR) - alpha E / (E_hover K).

    Args:
        sr: (...) served ratios; energy_j: (...) fleet energy of the slot (joules); scenario: the constants.
    """
    hover_j = hover_power(scenario.rotor) * scenario.slot_s
    return sr - scenario.reward_beta * (1.0 - sr) - scenario.reward_alpha * energy_j / (hover_j * scenario.n_uavs)


def episode_rewards(fleet: torch.Tensor, actions: torch.Tensor, next_sr: torch.Tensor, grid, scenario) -> torch.Tensor:
    """Rewards (T,) of one recorded day: fleet (T+1, K, 7), actions (T, K, 3), next_sr (T,)."""
    state = fleet_state_from_obs(fleet[:-1].numpy(), grid, scenario)
    _, energy = fleet_step(state, actions.clamp(-1.0, 1.0), grid.geometry(), scenario)
    return step_reward(next_sr, energy.sum(-1), scenario).float()


class TransitionReplay(SequenceReplay):
    """Episodes (one training day each) with rewards and termination flags; see the module docstring."""

    def __init__(self, *, grid, scenario, demand: np.ndarray, day_ids: np.ndarray):
        """Args: grid, scenario: of the training core; demand: (D, S, R, C) its days; day_ids: (D,) their tensor
        day indices."""
        geom = grid.geometry()
        super().__init__(demand=demand, day_ids=day_ids, window=scenario.obs_window, width_m=geom.width_m,
                         height_m=geom.height_m, slots_per_day=scenario.slots_per_day)
        self.grid, self.scenario = grid, scenario
        self.rewards: list[torch.Tensor] = []      # (T,)
        self.terminated: list[torch.Tensor] = []   # (T,) bool
        self.own: list[bool] = []                  # False: the pre-collection; True: TD-MPC's own episode
        self._stacked = None
        self._scaled = {}                          # dtype: scale_demand of every map in it, computed on first use

    @classmethod
    def from_precollected(cls, replay: SequenceReplay, *, grid, scenario) -> "TransitionReplay":
        """The pre-collected episodes, in their order, with their rewards recomputed (:func:`episode_rewards`)."""
        out = cls(grid=grid, scenario=scenario, demand=replay.demand.numpy(), day_ids=replay.day_ids)
        for row, fl, act, sr in zip(replay.rows, replay.fleet, replay.actions, replay.next_sr):
            out.add_episode(row=row, fleet=fl.numpy(), actions=act.numpy(), next_sr=sr.numpy(), own=False)
        return out

    def add_episode(self, *, row: int, fleet: np.ndarray, actions: np.ndarray, next_sr: np.ndarray,
                    reward: np.ndarray | None = None, terminated: np.ndarray | None = None, own: bool = True) -> None:
        """Store one day (see ``SequenceReplay.add_episode``); ``reward`` (T,) defaults to :func:`episode_rewards`,
        ``terminated`` (T,) to all False (the environment never terminates)."""
        super().add_episode(row=row, fleet=fleet, actions=actions, next_sr=next_sr)
        t = self.actions[-1].shape[0]
        rew = episode_rewards(self.fleet[-1], self.actions[-1], self.next_sr[-1], self.grid, self.scenario) \
            if reward is None else torch.as_tensor(np.asarray(reward, dtype=np.float32))
        term = torch.zeros(t, dtype=torch.bool) if terminated is None else torch.as_tensor(np.asarray(terminated,
                                                                                                      dtype=bool))
        if rew.shape != (t,) or term.shape != (t,):
            raise ValueError(f"TransitionReplay.add_episode: expected reward and terminated of shape ({t},), found "
                             f"{tuple(rew.shape)} and {tuple(term.shape)}")
        self.rewards.append(rew)
        self.terminated.append(term)
        self.own.append(bool(own))
        self._stacked = None

    def mean_reward(self, own: bool | None = None) -> float:
        """Mean reward per transition of the own (True), pre-collected (False) or all (None) episodes."""
        r = [x for x, o in zip(self.rewards, self.own) if own is None or o == own]
        return float(torch.cat(r).mean()) if r else float("nan")

    def _stack(self):
        if self._stacked is None:
            self._stacked = (torch.stack(self.fleet), torch.stack(self.actions), torch.stack(self.rewards),
                             torch.stack(self.terminated), torch.as_tensor(self.rows))
        return self._stacked

    def scaled_maps(self, dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """(D, S, R, C) the encoder's scaling of every stored map (``model.scale_demand``), computed once: a window
        then reads its maps transformed instead of transforming w+1 maps per observation per batch. In ``dtype``:
        the float32 values rounded once (to nearest), as the encoder's bfloat16 input buffer rounds them, so a
        bfloat16 step reads the values it would have rounded itself, at half the bytes and without a cast per
        observation (each map is read by w+1 overlapping windows)."""
        if dtype not in self._scaled:
            self._scaled[dtype] = scale_demand(self.demand).to(dtype)     # float32: the same tensor, no copy
        return self._scaled[dtype]

    def scaled_windows(self, row: torch.Tensor, start: torch.Tensor, length: int,
                       dtype: torch.dtype = torch.float32) -> torch.Tensor:
        """The windows of slots start..start+length-1 of each of B sequences, from :meth:`scaled_maps` in ``dtype``,
        as a view (length, B, w+1, R, C) of one strip of the maps x_{s-w..s+length-1} per sequence (edge-padded as
        ``window_maps`` pads): the same values as ``window_maps`` with w+1 times fewer maps read."""
        strip = self.strip_maps(row, start, length, self.scaled_maps(dtype))        # (B, length + w, R, C)
        b, _, r, c = strip.shape
        st = strip.stride()
        return strip.as_strided((length, b, self.window + 1, r, c), (st[1], st[0], st[1], st[2], st[3]))

    def sample_windows(self, batch: int, horizon: int, generator: torch.Generator, *,
                       scaled: bool = False, dtype: torch.dtype = torch.float32) -> dict[str, torch.Tensor]:
        """``batch`` windows of H+1 consecutive observations of one day (H = ``horizon``), uniformly.

        Args:
            scaled: give the windows' maps as ``scaled_demand``, a view into strips of :meth:`scaled_maps` (the
                same values as the encoder's scaling of ``demand``; :meth:`scaled_windows`), in place of
                ``demand``.
            dtype: the scaled maps' dtype (:meth:`scaled_maps`); float32 unless ``scaled``.
        Returns:
            dict with ``demand`` (H+1, B, w+1, R, C) (or ``scaled_demand``), ``fleet`` (H+1, B, K, 7), ``time``
            (H+1, B, 2), ``action`` (H, B, 3K), ``reward`` (H, B), ``terminated`` (H, B) bool.
        """
        if not self.rows:
            raise ValueError("TransitionReplay.sample_windows: the buffer is empty")
        if dtype != torch.float32 and not scaled:
            raise ValueError(f"TransitionReplay.sample_windows: dtype {dtype} needs scaled=True (the raw maps are "
                             "float32)")
        fleet, actions, rewards, term, rows = self._stack()
        n_dec = actions.shape[1]
        if horizon > n_dec:
            raise ValueError(f"TransitionReplay.sample_windows: horizon {horizon} exceeds the episode length {n_dec}")
        eps = torch.randint(len(self.rows), (batch,), generator=generator)
        start = torch.randint(n_dec - horizon + 1, (batch,), generator=generator)
        slot = start.unsqueeze(0) + torch.arange(horizon + 1).unsqueeze(1)          # (H+1, B)
        ep = eps.unsqueeze(0).expand_as(slot)
        row = rows[eps].unsqueeze(0).expand_as(slot)
        maps = {"scaled_demand": self.scaled_windows(rows[eps], start, horizon + 1, dtype)} if scaled else \
            {"demand": self.window_maps(row, slot)}
        return {**maps, "fleet": fleet[ep, slot], "time": self.time_features(slot),
                "action": actions[ep[:-1], slot[:-1]].flatten(-2), "reward": rewards[ep[:-1], slot[:-1]],
                "terminated": term[ep[:-1], slot[:-1]]}

    def state_dict(self) -> dict:
        return {**super().state_dict(), "rewards": self.rewards, "terminated": self.terminated, "own": self.own}

    @classmethod
    def from_state_dict(cls, sd: dict, *, grid, scenario) -> "TransitionReplay":
        rep = cls(grid=grid, scenario=scenario, demand=sd["demand"].numpy(), day_ids=sd["day_ids"])
        rep.rows, rep.fleet, rep.actions, rep.next_sr = list(sd["rows"]), sd["fleet"], sd["actions"], sd["next_sr"]
        rep.rewards, rep.terminated, rep.own = list(sd["rewards"]), list(sd["terminated"]), list(sd["own"])
        return rep
