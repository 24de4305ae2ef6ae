"""The one flat observation and flat action of every model-free learning method.

Flat observation (B, D) float32, in this order:

* ``log1p`` of the demand maps x_{t-w..t} (w + 1 maps of rows x cols, row-major): the fixed
  :data:`DEMAND_TRANSFORM`, the same for every method and every dataset, with nothing fitted. Demand is the
  prepared tensor's (training p99 times kappa), so hotspots reach values of several units while most cells are
  near 0; log1p keeps zeros at 0, is monotone, and compresses the peaks to the scale of the other features.
* the fleet, K x 7 features (``dswm.sim.core.FLEET_FEATURES``: x/W, y/H, battery fraction, active, returning,
  charging, charge_left / recharge slots), all in [0, 1];
* the time phase (sin, cos of 2 pi t / slots_per_day).

D = (w + 1) * rows * cols + 7 K + 2 (:func:`observation_dim`). Flat action (B, 3K): the (K, 3) action of
``dswm.sim.core.FleetCore`` (dx, dy as a fraction of D_max, bandwidth logit) flattened UAV by UAV.
"""
from __future__ import annotations

from typing import Any, Mapping

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from dswm.sim.core import FLEET_FEATURES
from dswm.sim.scenario import Scenario

DEMAND_TRANSFORM = "log1p"
"""The transform of the demand maps in the flat observation (numpy's log1p, elementwise)."""

ACTION_DIM = 3
"""Per-UAV action components: dx, dy, bandwidth logit."""


def observation_dim(grid_rows: int, grid_cols: int, scenario: Scenario) -> int:
    """D, the length of the flat observation of a ``grid_rows x grid_cols`` grid under ``scenario``."""
    return ((scenario.obs_window + 1) * grid_rows * grid_cols + scenario.n_uavs * len(FLEET_FEATURES) + 2)


def flat_observation(obs: Mapping[str, Any]) -> np.ndarray:
    """The flat observation of a batch.

    Args:
        obs: {"demand": (B, w+1, R, C), "fleet": (B, K, 7), "time": (B, 2)} (``FleetCore``'s observation).

    Returns:
        (B, D) float32: log1p(demand), fleet, time, each flattened row-major.
    """
    demand = np.asarray(obs["demand"], dtype=np.float32)
    b = demand.shape[0]
    out = np.concatenate([np.log1p(demand.reshape(b, -1)),
                          np.asarray(obs["fleet"], dtype=np.float32).reshape(b, -1),
                          np.asarray(obs["time"], dtype=np.float32).reshape(b, -1)], axis=1)
    return out


def observation_space(grid_rows: int, grid_cols: int, scenario: Scenario) -> spaces.Box:
    """Box (D,) of the flat observation: demand in [0, inf), fleet in [0, 1], time in [-1, 1]."""
    n_demand = (scenario.obs_window + 1) * grid_rows * grid_cols
    n_fleet = scenario.n_uavs * len(FLEET_FEATURES)
    low = np.concatenate([np.zeros(n_demand + n_fleet), -np.ones(2)]).astype(np.float32)
    high = np.concatenate([np.full(n_demand, np.inf), np.ones(n_fleet + 2)]).astype(np.float32)
    return spaces.Box(low, high, dtype=np.float32)


def action_space(n_uavs: int) -> spaces.Box:
    """Box(-1, 1, (3K,)) of the flat action."""
    return spaces.Box(-1.0, 1.0, (n_uavs * ACTION_DIM,), np.float32)


def flat_action(actions: np.ndarray) -> np.ndarray:
    """(B, K, 3) -> (B, 3K) float32."""
    a = np.asarray(actions, dtype=np.float32)
    return a.reshape(a.shape[0], -1)


def fleet_action(flat: np.ndarray, n_uavs: int) -> np.ndarray:
    """(B, 3K) -> (B, K, 3) float32; raises ValueError on a wrong width."""
    a = np.asarray(flat, dtype=np.float32)
    if a.ndim != 2 or a.shape[1] != n_uavs * ACTION_DIM:
        raise ValueError(f"flat action: expected shape (B, {n_uavs * ACTION_DIM}), found {a.shape}")
    return a.reshape(a.shape[0], n_uavs, ACTION_DIM)


class FlatFleetEnv(gym.Wrapper):
    """The Gymnasium view ``dswm.sim.env.UAVFleetEnv`` with the flat observation and the flat action: one day
    per episode, what an SB3 policy sees (:class:`dswm.methods.rl.vec_env.FleetVecEnv` steps many at once)."""

    def __init__(self, env):
        super().__init__(env)
        core = env.unwrapped.core
        self.n_uavs = core.scenario.n_uavs
        self.observation_space = observation_space(core.grid.rows, core.grid.cols, core.scenario)
        self.action_space = action_space(self.n_uavs)

    @staticmethod
    def _flat(obs: Mapping[str, Any]) -> np.ndarray:
        return flat_observation({k: np.asarray(v)[None] for k, v in obs.items()})[0]

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        obs, info = self.env.reset(seed=seed, options=options)
        return self._flat(obs), info

    def step(self, action):
        obs, reward, terminated, truncated, info = self.env.step(fleet_action(np.asarray(action)[None],
                                                                              self.n_uavs)[0])
        return self._flat(obs), reward, terminated, truncated, info
