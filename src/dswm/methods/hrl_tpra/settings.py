"""HRL-TPRA's settings (config.yaml ``methods.hrl_tpra``, one profile's budget merged in)."""
from __future__ import annotations

import dataclasses

from dswm.config import ConfigError, check_fields, setting

ARCHITECTURE_KEYS = ("candidates", "crop_radius", "pointer_hidden", "actor_hidden", "actor_depth", "fine_scale",
                     "tanh_clip", "macro_slots")
"""The settings that shape the networks and their inputs: a model file is loaded only under the same values."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class HRLTPRASettings:
    """The two levels, their optimization and the budget of HRL-TPRA (all of them shape training)."""

    # ---- the high level: pointer-network trajectory planner
    macro_slots: int = setting("count")
    """Slots per macro-slot: the planner assigns target cells at slots 0, m, 2m, ... of a day."""
    candidates: int = setting("count")
    """N, the top-N demand cells of the current observed map the planner chooses from (at least K, checked at fit)."""
    pointer_hidden: int = setting("count")
    """Width of the planner's encoder, decoder (GRU) and attention, and of its value network."""
    tanh_clip: float = setting("positive")
    """C of the pointer logits C tanh(u) (Bello et al. 2016): bounds the logits, keeps the choice exploratory."""
    # ---- the low level: per-UAV resource actors
    crop_radius: int = setting("natural")
    """Half-width in cells of a UAV's local context: it sees (2 r + 1)^2 cells of demand and occupancy."""
    actor_hidden: int = setting("count")
    """Width of each UAV's actor and critic hidden layers (separate weights per UAV)."""
    actor_depth: int = setting("count")
    """Hidden layers (Linear + ReLU) of each actor and critic, then a linear head."""
    fine_scale: float = setting(
        schema={"type": "number", "exclusiveMinimum": 0, "maximum": 2,
                "description": "a number in (0, 2] (a fraction of D_max)"})
    """Reach of the fine move as a fraction of D_max: (dx, dy) = toward-target + fine_scale * actor output."""
    log_std_init: float = setting("number")
    """Initial log std of each UAV's Gaussian over its three outputs (learned, one per UAV and output)."""
    # ---- optimization
    gamma: float = setting("below_one")
    """Discount per slot of the low level's returns (GAE)."""
    gae_lambda: float = setting("fraction")
    """GAE lambda of the low level."""
    high_gamma: float = setting("below_one")
    """Discount per macro-slot of the planner's bootstrap (0: the macro-slot's summed reward alone)."""
    clip_range: float = setting("positive")
    """PPO ratio clipping, both levels."""
    ent_coef: float = setting("nonnegative")
    """Weight of the Gaussian entropy bonus of the resource actors."""
    high_ent_coef: float = setting("nonnegative")
    """Weight of the pointer's entropy bonus (the sum over its K choices)."""
    lr: float = setting("positive")
    """Adam learning rate of the resource actors and their critics."""
    high_lr: float = setting("positive")
    """Adam learning rate of the planner and its value network."""
    max_grad_norm: float = setting("positive")
    """Largest gradient norm of each network per step."""
    n_envs: int = setting("count")
    """Training days stepped together per round (one core call per slot)."""
    day_episodes: int = setting("count")
    """Day-episodes in all, a multiple of n_envs (each 143 transitions)."""
    n_epochs: int = setting("count")
    """Passes of the resource actors over each round's day-slots."""
    high_epochs: int = setting("count")
    """Passes of the planner over each round's macro decisions (its serial decoding makes a pass costly)."""
    batch_size: int = setting("count")
    """Resource actors' minibatch in day-slots (each holds the K UAVs)."""
    high_batch_size: int = setting("count")
    """Planner's minibatch in macro decisions (a round holds n_envs x ceil(143 / macro_slots) of them)."""
    log_points: int = setting("count")
    """Most entries of the training history (each the mean over a window of rounds)."""
    checkpoint_every: int = setting("count")
    """Rounds between two checkpoints (one is also written at the end)."""

    def __post_init__(self):
        where = "methods.hrl_tpra"
        check_fields(self, where)
        if self.day_episodes % self.n_envs:
            raise ConfigError(f"config key {where}.day_episodes: expected a multiple of n_envs = {self.n_envs}, "
                              f"found {self.day_episodes}")

    def architecture(self) -> dict:
        """The values of :data:`ARCHITECTURE_KEYS`."""
        return {k: getattr(self, k) for k in ARCHITECTURE_KEYS}
