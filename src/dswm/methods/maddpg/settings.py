"""MADDPG's settings (config.yaml ``methods.maddpg``, one profile's budget merged in)."""
from __future__ import annotations

import dataclasses

from dswm.config import ENUM, ConfigError, check_fields, setting
from dswm.methods.matmul import MatmulDtype

ARCHITECTURE_KEYS = ("crop_radius", "index_embed", "actor_hidden", "actor_depth", "critic_hidden", "critic_depth")
"""The settings that shape the networks: a model file is loaded only under the same values."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class MADDPGSettings:
    """Networks, optimization and budget of MADDPG (all of them shape training)."""

    crop_radius: int = setting("natural")
    """Half-width in cells of a UAV's local crop: it sees (2 r + 1)^2 cells around its own cell."""
    index_embed: int = setting("count")
    """Width of the learned UAV-index embedding appended to the shared actor's local input."""
    actor_hidden: int = setting("count")
    """Width of the actor's hidden layers (the last one is the per-agent embedding that is monitored)."""
    actor_depth: int = setting("count")
    """Hidden layers of the actor (each Linear + ReLU), then a linear head to the 3 pre-tanh outputs."""
    critic_hidden: int = setting("count")
    """Width of the centralized critic's hidden layers."""
    critic_depth: int = setting("count")
    """Hidden layers of the critic (the first one takes the joint observation and the joint action)."""
    actor_lr: float = setting("positive")
    """Adam learning rate of the actor."""
    critic_lr: float = setting("positive")
    """Adam learning rate of the critic."""
    gamma: float = setting("below_one")
    """Discount per slot in the TD target."""
    tau: float = setting("discount")
    """Polyak rate of the target networks, theta' <- tau theta + (1 - tau) theta' after every gradient step."""
    noise_std: float = setting("nonnegative")
    """Std of the Gaussian exploration noise added to every action component (then clipped to [-1, 1])."""
    action_reg: float = setting("nonnegative")
    """Weight of the mean squared pre-tanh actor output in the actor loss (keeps tanh out of saturation)."""
    grad_clip: float = setting("positive")
    """Largest gradient norm of each network per step."""
    buffer_size: int = setting("count")
    """Replay capacity in transitions (oldest overwritten first)."""
    batch_size: int = setting("count")
    """Transitions per gradient step."""
    warmup: int = setting("natural")
    """Transitions with uniform random actions before the actor acts and the first gradient step."""
    transitions: int = setting("count")
    """Environment transitions in all: whole day-episodes, a multiple of slots_per_day - 1."""
    update_every: int = setting("count")
    """Environment transitions between two rounds of gradient steps."""
    gradient_steps: int = setting("count")
    """Gradient steps (critic, actor, targets) per round."""
    log_points: int = setting("count")
    """Most entries of the training history (each the mean over a window of day-episodes)."""
    checkpoint_every: int = setting("count")
    """Day-episodes between two checkpoints (one is also written at the end)."""
    matmul_dtype: MatmulDtype = setting(ENUM)
    """The dtype of the networks' matrix products, float32 everything else (:mod:`dswm.methods.matmul`)."""

    def __post_init__(self):
        where = "methods.maddpg"
        check_fields(self, where)
        if self.batch_size > self.buffer_size:
            raise ConfigError(f"config key {where}.batch_size: expected at most buffer_size = {self.buffer_size}, "
                              f"found {self.batch_size}")

    def architecture(self) -> dict:
        """The values of :data:`ARCHITECTURE_KEYS`."""
        return {k: getattr(self, k) for k in ARCHITECTURE_KEYS}
