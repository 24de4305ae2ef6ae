"""MADDPG's settings (config.yaml ``methods.maddpg``, one profile's budget merged in)."""
from __future__ import annotations

import dataclasses

from dswm.config import ConfigError

ARCHITECTURE_KEYS = ("crop_radius", "index_embed", "actor_hidden", "actor_depth", "critic_hidden", "critic_depth")
"""The settings that shape the networks: a model file is loaded only under the same values."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class MADDPGSettings:
    """Networks, optimization and budget of MADDPG (all of them shape training)."""

    crop_radius: int
    """Half-width in cells of a UAV's local crop: it sees (2 r + 1)^2 cells around its own cell."""
    index_embed: int
    """Width of the learned UAV-index embedding appended to the shared actor's local input."""
    actor_hidden: int
    """Width of the actor's hidden layers (the last one is the per-agent embedding that is monitored)."""
    actor_depth: int
    """Hidden layers of the actor (each Linear + ReLU), then a linear head to the 3 pre-tanh outputs."""
    critic_hidden: int
    """Width of the centralized critic's hidden layers."""
    critic_depth: int
    """Hidden layers of the critic (the first one takes the joint observation and the joint action)."""
    actor_lr: float
    """Adam learning rate of the actor."""
    critic_lr: float
    """Adam learning rate of the critic."""
    gamma: float
    """Discount per slot in the TD target."""
    tau: float
    """Polyak rate of the target networks, theta' <- tau theta + (1 - tau) theta' after every gradient step."""
    noise_std: float
    """Std of the Gaussian exploration noise added to every action component (then clipped to [-1, 1])."""
    action_reg: float
    """Weight of the mean squared pre-tanh actor output in the actor loss (keeps tanh out of saturation)."""
    grad_clip: float
    """Largest gradient norm of each network per step."""
    buffer_size: int
    """Replay capacity in transitions (oldest overwritten first)."""
    batch_size: int
    """Transitions per gradient step."""
    warmup: int
    """Transitions with uniform random actions before the actor acts and the first gradient step."""
    transitions: int
    """Environment transitions in all: whole day-episodes, a multiple of slots_per_day - 1."""
    update_every: int
    """Environment transitions between two rounds of gradient steps."""
    gradient_steps: int
    """Gradient steps (critic, actor, targets) per round."""
    log_points: int
    """Most entries of the training history (each the mean over a window of day-episodes)."""
    checkpoint_every: int
    """Day-episodes between two checkpoints (one is also written at the end)."""

    def __post_init__(self):
        where = "methods.maddpg"
        for key in ("index_embed", "actor_hidden", "actor_depth", "critic_hidden", "critic_depth", "buffer_size",
                    "batch_size", "transitions", "update_every", "gradient_steps", "log_points",
                    "checkpoint_every"):
            if not isinstance(getattr(self, key), int) or getattr(self, key) < 1:
                raise ConfigError(f"config key {where}.{key}: expected an integer >= 1, found {getattr(self, key)!r}")
        for key in ("crop_radius", "warmup"):
            if not isinstance(getattr(self, key), int) or getattr(self, key) < 0:
                raise ConfigError(f"config key {where}.{key}: expected an integer >= 0, found {getattr(self, key)!r}")
        for key in ("actor_lr", "critic_lr", "grad_clip"):
            if not getattr(self, key) > 0:
                raise ConfigError(f"config key {where}.{key}: expected a number > 0, found {getattr(self, key)!r}")
        for key in ("noise_std", "action_reg"):
            if not getattr(self, key) >= 0:
                raise ConfigError(f"config key {where}.{key}: expected a number >= 0, found {getattr(self, key)!r}")
        if not 0 <= self.gamma < 1:
            raise ConfigError(f"config key {where}.gamma: expected a number in [0, 1), found {self.gamma!r}")
        if not 0 < self.tau <= 1:
            raise ConfigError(f"config key {where}.tau: expected a number in (0, 1], found {self.tau!r}")
        if self.batch_size > self.buffer_size:
            raise ConfigError(f"config key {where}.batch_size: expected at most buffer_size = {self.buffer_size}, "
                              f"found {self.batch_size}")

    def architecture(self) -> dict:
        """The values of :data:`ARCHITECTURE_KEYS`."""
        return {k: getattr(self, k) for k in ARCHITECTURE_KEYS}
