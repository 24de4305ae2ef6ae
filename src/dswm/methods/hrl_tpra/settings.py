"""HRL-TPRA's settings (config.yaml ``methods.hrl_tpra``, one profile's budget merged in)."""
from __future__ import annotations

import dataclasses

from dswm.config import ConfigError

ARCHITECTURE_KEYS = ("candidates", "crop_radius", "pointer_hidden", "actor_hidden", "actor_depth", "fine_scale",
                     "tanh_clip", "macro_slots")
"""The settings that shape the networks and their inputs: a model file is loaded only under the same values."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class HRLTPRASettings:
    """The two levels, their optimization and the budget of HRL-TPRA (all of them shape training)."""

    # ---- the high level: pointer-network trajectory planner
    macro_slots: int
    """Slots per macro-slot: the planner assigns target cells at slots 0, m, 2m, ... of a day."""
    candidates: int
    """N, the top-N demand cells of the current observed map the planner chooses from (at least K, checked at fit)."""
    pointer_hidden: int
    """Width of the planner's encoder, decoder (GRU) and attention, and of its value network."""
    tanh_clip: float
    """C of the pointer logits C tanh(u) (Bello et al. 2016): bounds the logits, keeps the choice exploratory."""
    # ---- the low level: per-UAV resource actors
    crop_radius: int
    """Half-width in cells of a UAV's local context: it sees (2 r + 1)^2 cells of demand and occupancy."""
    actor_hidden: int
    """Width of each UAV's actor and critic hidden layers (separate weights per UAV)."""
    actor_depth: int
    """Hidden layers (Linear + ReLU) of each actor and critic, then a linear head."""
    fine_scale: float
    """Reach of the fine move as a fraction of D_max: (dx, dy) = toward-target + fine_scale * actor output."""
    log_std_init: float
    """Initial log std of each UAV's Gaussian over its three outputs (learned, one per UAV and output)."""
    # ---- optimization
    gamma: float
    """Discount per slot of the low level's returns (GAE)."""
    gae_lambda: float
    """GAE lambda of the low level."""
    high_gamma: float
    """Discount per macro-slot of the planner's bootstrap (0: the macro-slot's summed reward alone)."""
    clip_range: float
    """PPO ratio clipping, both levels."""
    ent_coef: float
    """Weight of the Gaussian entropy bonus of the resource actors."""
    high_ent_coef: float
    """Weight of the pointer's entropy bonus (the sum over its K choices)."""
    lr: float
    """Adam learning rate of the resource actors and their critics."""
    high_lr: float
    """Adam learning rate of the planner and its value network."""
    max_grad_norm: float
    """Largest gradient norm of each network per step."""
    n_envs: int
    """Training days stepped together per round (one core call per slot)."""
    day_episodes: int
    """Day-episodes in all, a multiple of n_envs (each 143 transitions)."""
    n_epochs: int
    """Passes of the resource actors over each round's day-slots."""
    high_epochs: int
    """Passes of the planner over each round's macro decisions (its serial decoding makes a pass costly)."""
    batch_size: int
    """Resource actors' minibatch in day-slots (each holds the K UAVs)."""
    high_batch_size: int
    """Planner's minibatch in macro decisions (a round holds n_envs x ceil(143 / macro_slots) of them)."""
    log_points: int
    """Most entries of the training history (each the mean over a window of rounds)."""
    checkpoint_every: int
    """Rounds between two checkpoints (one is also written at the end)."""

    def __post_init__(self):
        where = "methods.hrl_tpra"
        for key in ("macro_slots", "candidates", "pointer_hidden", "actor_hidden", "actor_depth", "n_envs",
                    "day_episodes", "n_epochs", "high_epochs", "batch_size", "high_batch_size", "log_points",
                    "checkpoint_every"):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ConfigError(f"config key {where}.{key}: expected an integer >= 1, found {value!r}")
        if isinstance(self.crop_radius, bool) or not isinstance(self.crop_radius, int) or self.crop_radius < 0:
            raise ConfigError(f"config key {where}.crop_radius: expected an integer >= 0, found {self.crop_radius!r}")
        for key in ("tanh_clip", "fine_scale", "clip_range", "lr", "high_lr", "max_grad_norm"):
            if not getattr(self, key) > 0:
                raise ConfigError(f"config key {where}.{key}: expected a number > 0, found {getattr(self, key)!r}")
        for key in ("ent_coef", "high_ent_coef"):
            if not getattr(self, key) >= 0:
                raise ConfigError(f"config key {where}.{key}: expected a number >= 0, found {getattr(self, key)!r}")
        for key in ("gamma", "high_gamma"):
            value = getattr(self, key)
            if not 0 <= value < 1:
                raise ConfigError(f"config key {where}.{key}: expected a number in [0, 1), found {value!r}")
        if not 0 <= self.gae_lambda <= 1:
            raise ConfigError(f"config key {where}.gae_lambda: expected a number in [0, 1], found {self.gae_lambda!r}")
        if self.fine_scale > 2:
            raise ConfigError(f"config key {where}.fine_scale: expected a number in (0, 2] (a fraction of D_max), "
                              f"found {self.fine_scale!r}")
        if self.day_episodes % self.n_envs:
            raise ConfigError(f"config key {where}.day_episodes: expected a multiple of n_envs = {self.n_envs}, "
                              f"found {self.day_episodes}")

    def architecture(self) -> dict:
        """The values of :data:`ARCHITECTURE_KEYS`."""
        return {k: getattr(self, k) for k in ARCHITECTURE_KEYS}
