"""``FleetVecEnv``: Stable-Baselines3's ``VecEnv`` over the batched ``FleetCore``.

The n_envs episodes are n_envs training days stepped by ONE ``FleetCore.step`` call per slot. A round is n_envs
day-episodes started together: each draws its day from the core's days with a numpy ``Generator`` seeded from the
seed (:meth:`FleetVecEnv.seed`); all last 143 decisions, so they end together. At the day's end every episode is
done with ``TimeLimit.truncated`` True (the day is cut by time, nothing terminates it, so TD targets bootstrap),
``terminal_observation`` the last observation and ``episode`` its return; the next round starts at once with new
days (auto-reset).

Record of the days used: :attr:`FleetVecEnv.episodes` lists the core day of every FINISHED day-episode in the
order they finished (:meth:`FleetVecEnv.episode_days` maps them to tensor days through ``core.day_ids``). An
episode still running (a round in progress) is not listed: training budgets are whole rounds, so every transition
a learner used belongs to a listed episode and ``transitions == 143 * len(episodes)`` (:attr:`transitions`
counts every step taken, finished or not, to prove it).
"""
from __future__ import annotations

import time
from typing import Any, Sequence

import numpy as np
from stable_baselines3.common.vec_env import VecEnv

from dswm.methods.rl.spaces import action_space, fleet_action, flat_observation, observation_space
from dswm.sim.core import FleetCore


class FleetVecEnv(VecEnv):
    """n_envs one-day episodes of one FleetCore, stepped together.

    Args:
        core: a FleetCore (of TRAINING days when it trains); ``core.day_ids`` maps its days to tensor days
            (``np.arange(core.n_days)`` when absent).
        n_envs: episodes stepped together.
        seed: seed of the day draws.

    Attribute, method and wrapper queries (``get_attr``, ``env_method``, ...) address this one object for every
    index: the n_envs episodes share it.
    """

    render_mode = None

    def __init__(self, core: FleetCore, *, n_envs: int, seed: int):
        if n_envs < 1:
            raise ValueError(f"n_envs: expected an integer >= 1, found {n_envs}")
        self.core = core
        self.day_ids = np.asarray(getattr(core, "day_ids", np.arange(core.n_days)), dtype=np.int64)
        self.n_uavs = core.scenario.n_uavs
        self.horizon = core.scenario.slots_per_day - 1
        self.episodes: list[int] = []
        self.transitions = 0
        self.current_days = np.zeros(0, dtype=np.int64)
        self._finished: list[tuple[float, float]] = []
        self._actions: np.ndarray | None = None
        self.seed(seed)
        super().__init__(n_envs, observation_space(core.grid.rows, core.grid.cols, core.scenario),
                         action_space(self.n_uavs))

    # ---- episodes ------------------------------------------------------------------------------------
    def seed(self, seed: int | None = None) -> Sequence[int | None]:
        """Re-seed the day draws (effective from the next round)."""
        if seed is None:
            seed = int(np.random.randint(0, np.iinfo(np.uint32).max, dtype=np.uint32))
        self._rng = np.random.default_rng(seed)
        return [seed] * self.num_envs if hasattr(self, "num_envs") else [seed]

    def _start_round(self) -> np.ndarray:
        """Draw n_envs core days, reset the core on them; (n_envs, D) first observations."""
        self.current_days = self._rng.integers(self.core.n_days, size=self.num_envs).astype(np.int64)
        return self._reset_core()

    def _reset_core(self) -> np.ndarray:
        obs = self.core.reset(self.current_days)
        self._return = np.zeros(self.num_envs)
        self._sr = np.zeros(self.num_envs)
        self._t0 = time.perf_counter()
        return flat_observation(obs)

    def reset(self) -> np.ndarray:
        """Start a new round (episodes in progress are dropped and not recorded)."""
        self._reset_seeds()
        self._reset_options()
        return self._start_round()

    def episode_days(self) -> list[int]:
        """Tensor day of every finished day-episode, in order."""
        return self.day_ids[np.asarray(self.episodes, dtype=np.int64)].tolist()

    def drain_finished(self) -> tuple[float, float, int]:
        """Mean return and mean served ratio of the episodes finished since the last call, and their count."""
        done, self._finished = self._finished, []
        if not done:
            return float("nan"), float("nan"), 0
        ret, sr = np.asarray(done).mean(axis=0)
        return float(ret), float(sr), len(done)

    # ---- stepping ------------------------------------------------------------------------------------
    def step_async(self, actions: np.ndarray) -> None:
        self._actions = np.asarray(actions, dtype=np.float32)

    def reward_of(self, out) -> np.ndarray:
        """(n_envs,) float32 reward the learner sees for one step of the core (``out``, a StepOutput): the
        paper's eq. 7 here; a multi-objective learner overrides it with its own scalarization."""
        return out.reward.astype(np.float32)

    def step_wait(self):
        """One slot of every episode: (obs (n_envs, D), reward (n_envs,) float32, done (n_envs,) bool, infos)."""
        if self._actions is None:
            raise RuntimeError("step_wait() without step_async()")
        out = self.core.step(fleet_action(self._actions, self.n_uavs))
        self._actions = None
        self.transitions += self.num_envs
        obs = flat_observation(out.obs)
        reward = self.reward_of(out)
        self._return += reward
        self._sr += out.sr
        terminated, truncated = np.asarray(out.terminated, bool), np.asarray(out.truncated, bool)
        dones = terminated | truncated
        infos: list[dict[str, Any]] = [{} for _ in range(self.num_envs)]
        if dones.any():
            if not dones.all():
                raise RuntimeError("FleetVecEnv: the episodes of a round must end together")
            elapsed = time.perf_counter() - self._t0
            for i, info in enumerate(infos):
                info["terminal_observation"] = obs[i]
                info["TimeLimit.truncated"] = bool(truncated[i] and not terminated[i])
                info["episode"] = {"r": float(self._return[i]), "l": self.core.t, "t": round(elapsed, 6)}
                info["day"] = int(self.day_ids[self.current_days[i]])
                self._finished.append((float(self._return[i]), float(self._sr[i] / self.core.t)))
            self.episodes.extend(self.current_days.tolist())
            obs = self._start_round()
        return obs, reward, dones, infos

    # ---- checkpoints ----------------------------------------------------------------------------------
    def state_dict(self) -> dict:
        """What resumes the day draws and the record at a round boundary (the core at slot 0)."""
        if self.core.t != 0:
            raise RuntimeError(f"FleetVecEnv.state_dict(): the round is at slot {self.core.t}; checkpoints are "
                               f"taken between rounds")
        return {"rng": self._rng.bit_generator.state, "current_days": self.current_days.tolist(),
                "episodes": list(self.episodes), "transitions": self.transitions}

    def load_state_dict(self, state: dict) -> np.ndarray:
        """Restore :meth:`state_dict` and reset the core on the round's days; (n_envs, D) its observations."""
        self._rng.bit_generator.state = state["rng"]
        self.current_days = np.asarray(state["current_days"], dtype=np.int64)
        self.episodes = [int(d) for d in state["episodes"]]
        self.transitions = int(state["transitions"])
        self._finished = []
        return self._reset_core()

    # ---- the rest of the VecEnv interface -------------------------------------------------------------
    def close(self) -> None:
        """Nothing to release."""

    def get_attr(self, attr_name: str, indices=None) -> list[Any]:
        return [getattr(self, attr_name) for _ in self._get_indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices=None) -> None:
        setattr(self, attr_name, value)

    def env_method(self, method_name: str, *method_args, indices=None, **method_kwargs) -> list[Any]:
        """Call the method once (the episodes share this object); its result repeated per index."""
        result = getattr(self, method_name)(*method_args, **method_kwargs)
        return [result for _ in self._get_indices(indices)]

    def env_is_wrapped(self, wrapper_class, indices=None) -> list[bool]:
        return [False for _ in self._get_indices(indices)]

    def get_images(self) -> Sequence[np.ndarray | None]:
        return [None for _ in range(self.num_envs)]
