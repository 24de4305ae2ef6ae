"""The three objectives of EMORL-TCTO on the environment: per step, the weighted reward the PPO learner sees,
and the deterministic measurement of a policy's objective vector on a fixed set of training days.

Per step (one slot of every episode, from the core's ``StepOutput``): served ratio SR_{t+1}, minus the fleet's
energy of the slot over the fleet's hover energy E_hover K (the normalization of the energy term of the core's
reward, eq. 7), and the slot's Jain index. A day's objective vector is the mean over its 143 decisions.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
import torch
from stable_baselines3.common.policies import ActorCriticPolicy

from dswm.methods.emorl_tcto.archive import N_OBJ
from dswm.methods.rl.spaces import action_space, flat_observation, fleet_action, observation_space
from dswm.methods.rl.vec_env import FleetVecEnv
from dswm.sim.core import FleetCore
from dswm.sim.energy import rotor_power


def energy_norm(core: FleetCore) -> float:
    """E_hover K in joules: the fleet's energy of a slot spent hovering (the core's reward normalization)."""
    return float(core.hover_energy_j * core.scenario.n_uavs)


def max_energy_ratio(scenario) -> float:
    """The largest slot energy of a UAV over its hover energy: P(V) / P(0) at the worse end of [0, V_max] (the
    rotary-wing power falls, then rises with speed, so its maximum on an interval is at an end)."""
    p0 = rotor_power(0.0, scenario.rotor)
    return float(max(p0, rotor_power(scenario.v_max_mps, scenario.rotor)) / p0)


def step_objectives(out, norm: float) -> np.ndarray:
    """(B, 3) float64 objectives of one step: served ratio, -energy / (E_hover K), Jain index."""
    return np.stack([np.asarray(out.sr, dtype=np.float64),
                     -np.asarray(out.energy_j, dtype=np.float64) / norm,
                     np.asarray(out.jain, dtype=np.float64)], axis=1)


class ObjectiveVecEnv(FleetVecEnv):
    """``FleetVecEnv`` whose reward is the scalarization ``weight . objectives`` of the current task.

    ``weight`` (3,) is set before each task (between rounds). Every finished day-episode's objective vector
    (its mean over the day) is appended to :attr:`objective_log`, in the order the episodes finish.
    """

    def __init__(self, core: FleetCore, *, n_envs: int, seed: int):
        super().__init__(core, n_envs=n_envs, seed=seed)
        self.norm = energy_norm(core)
        self.weight = np.full(N_OBJ, 1.0 / N_OBJ)
        self.objective_log: list[np.ndarray] = []
        self._objective_sum = np.zeros((n_envs, N_OBJ))

    def reward_of(self, out) -> np.ndarray:
        obj = step_objectives(out, self.norm)
        if self.core.t == 1:  # the first step of a round
            self._objective_sum[:] = 0.0
        self._objective_sum += obj
        if np.asarray(out.truncated, bool).all():  # the day's end: every episode of the round finishes here
            self.objective_log.extend(self._objective_sum / self.core.t)
        return (obj @ self.weight).astype(np.float32)


def make_policy(core_or_grid, scenario, *, net_arch: Sequence[int], log_std_init: float, learning_rate: float,
                device: str = "cpu") -> ActorCriticPolicy:
    """A fresh SB3 ``ActorCriticPolicy`` exactly as PPO's ``MlpPolicy`` builds it with these settings (separate
    actor and critic MLPs of ``net_arch``), on the flat observation of the grid and scenario. Its weights come
    from the global torch RNG."""
    grid = getattr(core_or_grid, "grid", core_or_grid)
    arch = list(net_arch)
    policy = ActorCriticPolicy(observation_space(grid.rows, grid.cols, scenario), action_space(scenario.n_uavs),
                               lambda _: learning_rate, net_arch={"pi": arch, "vf": list(arch)},
                               log_std_init=log_std_init)
    return policy.to(device)


def policy_actions(policy: ActorCriticPolicy, obs, n_uavs: int) -> np.ndarray:
    """(B, K, 3) float32 deterministic actions (the Gaussian's mean) of ``policy``, clipped to [-1, 1]."""
    action, _ = policy.predict(flat_observation(obs), deterministic=True)
    return np.clip(fleet_action(action, n_uavs), -1.0, 1.0).astype(np.float32)


@torch.no_grad()
def measure_objectives(policy: ActorCriticPolicy, core: FleetCore, days: Sequence[int]) -> np.ndarray:
    """(B, 3) objective vectors of ``policy`` acting deterministically on the core days ``days`` (one whole day
    each, stepped together). Consumes no random number."""
    obs = core.reset(days)
    total = np.zeros((len(days), N_OBJ))
    norm = energy_norm(core)
    for _ in range(core.scenario.slots_per_day - 1):
        out = core.step(policy_actions(policy, obs, core.scenario.n_uavs))
        total += step_objectives(out, norm)
        obs = out.obs
    return total / core.t


def evaluation_core(core: FleetCore) -> FleetCore:
    """A second core over the same TRAINING days as ``core`` (same demand, grid, scenario, initial deployment and
    labels), so that measuring a policy never disturbs the round the learner's environment is in."""
    demand = core.demand.detach().cpu().numpy().reshape(core.n_days, -1, core.grid.rows, core.grid.cols)
    other = FleetCore(demand=demand, grid=core.grid, scenario=core.scenario,
                      init_pos=core.init_pos.detach().cpu().numpy(), dataset=core.dataset,
                      day_labels=core.day_labels, device=str(core.device))
    other.day_ids = np.asarray(getattr(core, "day_ids", np.arange(core.n_days)), dtype=np.int64)
    return other
