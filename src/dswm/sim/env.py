"""The fleet environment: the batched core plus Gymnasium and PettingZoo views of it.

``dswm/UAVFleet-v0`` is a Gymnasium ``Env`` of one day per episode; ``UAVFleetParallelEnv`` is the same
world with one agent per UAV for multi-agent methods. Both step a ``FleetCore`` with a batch of one.
"""
from __future__ import annotations

from typing import Sequence

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from dswm.sim.scenario import Scenario
from dswm.sim.core import FLEET_FEATURES, FleetCore, Grid, StepOutput, initial_positions, validate_demand


ENV_ID = "dswm/UAVFleet-v0"


def default_scenario() -> Scenario:
    """The scenario of the repository's config.yaml (for environments built without one); u is
    ``dswm.sim.scenario.DEMO_INTENSITY`` when config.yaml says ``calibrate``."""
    from pathlib import Path

    from dswm.sim.scenario import load_scenario

    return load_scenario(Path(__file__).resolve().parents[3] / "config.yaml", standin=True)


def synthetic_demand(*, days: int = 2, rows: int = 10, cols: int = 10, slots: int = 144,
                     seed: int = 0) -> np.ndarray:
    """A small demand tensor with two hotspots circling the area during the day (for quick checks).

    Returns:
        (days, slots, rows, cols) float32, non-negative.
    """
    rng = np.random.default_rng(seed)
    r, c = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    out = np.zeros((days, slots, rows, cols), dtype=np.float32)
    for d in range(days):
        phase0 = rng.uniform(0, 2 * np.pi)
        for t in range(slots):
            ang = phase0 + 2 * np.pi * t / slots
            for sign in (1.0, -1.0):
                cr = (rows - 1) / 2 + sign * 0.3 * rows * np.sin(ang)
                cc = (cols - 1) / 2 + sign * 0.3 * cols * np.cos(ang)
                out[d, t] += np.exp(-((r - cr) ** 2 + (c - cc) ** 2) / 4.0)
    return out


class UAVFleetEnv(gym.Env):
    """One day per episode of the K-UAV fleet serving a demand tensor.

    Args:
        demand: (days, T, rows, cols) non-negative demand; a small synthetic tensor when omitted.
        grid: the dataset grid (a 235 m grid of the demand's shape when omitted).
        scenario: constants (config.yaml's when omitted).
        init_pos: (K, 2) initial positions; K-means of the mean demand map when omitted.
        dataset: dataset name (seeds the initial battery permutation of each day).
        day_labels: one label per demand day.
        days: the day indices episodes are drawn from (all days when omitted).
    """

    metadata = {"render_modes": []}

    def __init__(self, demand: np.ndarray | None = None, grid: Grid | None = None,
                 scenario: Scenario | None = None, init_pos: np.ndarray | None = None,
                 dataset: str = "synthetic", day_labels: Sequence[str] | None = None,
                 days: Sequence[int] | None = None):
        scenario = scenario or default_scenario()
        demand = synthetic_demand(slots=scenario.slots_per_day) if demand is None else demand
        if not isinstance(demand, np.ndarray) or demand.ndim != 4:
            raise ValueError(f"demand: expected a (days, T, rows, cols) array, found {np.shape(demand)}")
        grid = grid or Grid(rows=demand.shape[2], cols=demand.shape[3], cell_m=235.0)
        if init_pos is None:
            validate_demand(demand, grid, scenario)
            init_pos = initial_positions(demand.mean(axis=(0, 1)), grid, scenario.n_uavs, scenario.init.kmeans_seed)
        labels = list(day_labels) if day_labels is not None else [f"d{i}" for i in range(demand.shape[0])]
        self.core = FleetCore(demand=demand, grid=grid, scenario=scenario, init_pos=init_pos,
                              dataset=dataset, day_labels=labels)
        self.days = list(range(demand.shape[0])) if days is None else [int(d) for d in days]
        k, w = scenario.n_uavs, scenario.obs_window
        self.observation_space = spaces.Dict({
            "demand": spaces.Box(0.0, np.inf, (w + 1, grid.rows, grid.cols), np.float32),
            "fleet": spaces.Box(0.0, 1.0, (k, len(FLEET_FEATURES)), np.float32),
            "time": spaces.Box(-1.0, 1.0, (2,), np.float32),
        })
        self.action_space = spaces.Box(-1.0, 1.0, (k, 3), np.float32)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Start a day: ``options={"day": i}`` picks tensor day i, else one is drawn with the env's RNG."""
        super().reset(seed=seed)
        if options and "day" in options:
            day = int(options["day"])
        else:
            day = int(self.days[self.np_random.integers(len(self.days))])
        obs = self.core.reset([day])
        return _first(obs), {"day": day, "sr": float(self.core.sr0[0]), "slot": 0}

    def step(self, action):
        out: StepOutput = self.core.step(np.asarray(action, dtype=np.float32)[None])
        info = {"sr": float(out.sr[0]), "energy_j": float(out.energy_j[0]), "jain": float(out.jain[0]),
                "slot": self.core.t}
        return _first(out.obs), float(out.reward[0]), bool(out.terminated[0]), bool(out.truncated[0]), info


def _first(obs: dict) -> dict:
    return {key: value[0] for key, value in obs.items()}


class UAVFleetParallelEnv(ParallelEnv):
    """PettingZoo view: one agent per UAV, a shared team reward (the fleet's reward).

    Each agent observes the common observation plus a one-hot of its own index, and acts with its own
    (dx, dy, bw_logit). Constructor arguments are those of ``UAVFleetEnv``.
    """

    metadata = {"render_modes": [], "name": "uav_fleet_v0"}

    def __init__(self, **kwargs):
        self.env = UAVFleetEnv(**kwargs)
        k = self.env.core.scenario.n_uavs
        self.possible_agents = [f"uav_{i}" for i in range(k)]
        self.agents = []
        base = self.env.observation_space
        self._obs_space = spaces.Dict({**base.spaces, "agent": spaces.Box(0.0, 1.0, (k,), np.float32)})
        self._act_space = spaces.Box(-1.0, 1.0, (3,), np.float32)

    def observation_space(self, agent):
        return self._obs_space

    def action_space(self, agent):
        return self._act_space

    def _split(self, obs: dict) -> dict:
        eye = np.eye(len(self.possible_agents), dtype=np.float32)
        return {a: {**obs, "agent": eye[i]} for i, a in enumerate(self.possible_agents)}

    def reset(self, seed: int | None = None, options: dict | None = None):
        obs, info = self.env.reset(seed=seed, options=options)
        self.agents = list(self.possible_agents)
        return self._split(obs), {a: dict(info) for a in self.agents}

    def step(self, actions: dict):
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise ValueError(f"actions: missing an action for agent(s) {missing}")
        joint = np.stack([np.asarray(actions[a], dtype=np.float32) for a in self.possible_agents])
        obs, reward, terminated, truncated, info = self.env.step(joint)
        agents = list(self.agents)
        if terminated or truncated:
            self.agents = []
        return (self._split(obs), {a: reward for a in agents}, {a: terminated for a in agents},
                {a: truncated for a in agents}, {a: dict(info) for a in agents})


def register_envs() -> None:
    """Register ``dswm/UAVFleet-v0`` with Gymnasium (idempotent; also the package's plugin entry point)."""
    if ENV_ID not in gym.registry:
        gym.register(id=ENV_ID, entry_point="dswm.sim.env:UAVFleetEnv")


register_envs()
