"""GA-MATR's settings (config.yaml ``methods.ga_matr``, one profile's budget merged in)."""
from __future__ import annotations

import dataclasses

from dswm.config import ConfigError

ARCHITECTURE_KEYS = ("crop_radius", "context_side", "d_model", "heads", "layers", "ffn_hidden", "critic_hidden",
                     "critic_depth")
"""The settings that shape the networks: a model file is loaded only under the same values."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class GAMATRSettings:
    """Networks, HAPPO optimization, fairness term and budget of GA-MATR (all of them shape training)."""

    crop_radius: int
    """Half-width in cells of a UAV token's local crop of the w+1 log1p demand maps ((2 r + 1)^2 cells)."""
    context_side: int
    """The demand maps are pooled (mean and max) to a P x P grid: P^2 demand-context tokens."""
    d_model: int
    """Width of every token (UAV and demand context)."""
    heads: int
    """Attention heads of each attention layer; must divide d_model."""
    layers: int
    """Graph-attention blocks: masked self-attention among UAVs, cross-attention to the context, feed-forward."""
    ffn_hidden: int
    """Hidden width of each block's feed-forward layer."""
    critic_hidden: int
    """Width of the centralized critic's hidden layers."""
    critic_depth: int
    """Hidden layers of the centralized critic (the first reads the flat global observation)."""
    actor_lr: float
    """Adam learning rate of the policy (every agent's sequential step)."""
    critic_lr: float
    """Adam learning rate of the critic."""
    gamma: float
    """Discount per slot."""
    gae_lambda: float
    """GAE lambda."""
    clip_eps: float
    """PPO clip: each agent's ratio is clipped to [1 - eps, 1 + eps] in its surrogate."""
    epochs: int
    """Passes over a rollout by EACH agent's sequential update (HAPPO's ppo_epoch)."""
    critic_epochs: int
    """Passes over a rollout by the critic."""
    minibatches: int
    """Minibatches per pass (of both the agents' and the critic's updates)."""
    entropy_coef: float
    """Weight of the updated agent's Gaussian entropy in its loss."""
    init_std: float
    """Initial std of every agent's Gaussian (state-independent, learned per agent and action component)."""
    max_grad_norm: float
    """Largest gradient norm of each optimizer step."""
    fairness_weight: float
    """Weight of the load-imbalance term (std / mean of the available UAVs' served load) taken off the learner's
    reward each slot; evaluation scores the environment's reward."""
    n_envs: int
    """Training days stepped together in one rollout (one round; its update follows)."""
    transitions: int
    """Environment transitions in all: whole rounds, a multiple of n_envs x (slots_per_day - 1)."""
    log_points: int
    """Most entries of the training history (each the mean over a window of rounds)."""
    checkpoint_every: int
    """Rounds between two checkpoints (one is also written at the end)."""

    def __post_init__(self):
        where = "methods.ga_matr"
        for key in ("context_side", "d_model", "heads", "layers", "ffn_hidden", "critic_hidden", "critic_depth",
                    "epochs", "critic_epochs", "minibatches", "n_envs", "transitions", "log_points",
                    "checkpoint_every"):
            value = getattr(self, key)
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ConfigError(f"config key {where}.{key}: expected an integer >= 1, found {value!r}")
        if not isinstance(self.crop_radius, int) or isinstance(self.crop_radius, bool) or self.crop_radius < 0:
            raise ConfigError(f"config key {where}.crop_radius: expected an integer >= 0, found {self.crop_radius!r}")
        if self.d_model % self.heads:
            raise ConfigError(f"config key {where}.heads: expected a divisor of d_model = {self.d_model}, "
                              f"found {self.heads}")
        for key in ("actor_lr", "critic_lr", "init_std", "max_grad_norm"):
            if not getattr(self, key) > 0:
                raise ConfigError(f"config key {where}.{key}: expected a number > 0, found {getattr(self, key)!r}")
        for key in ("entropy_coef", "fairness_weight"):
            if not getattr(self, key) >= 0:
                raise ConfigError(f"config key {where}.{key}: expected a number >= 0, found {getattr(self, key)!r}")
        if not 0 <= self.gamma < 1:
            raise ConfigError(f"config key {where}.gamma: expected a number in [0, 1), found {self.gamma!r}")
        if not 0 <= self.gae_lambda <= 1:
            raise ConfigError(f"config key {where}.gae_lambda: expected a number in [0, 1], found {self.gae_lambda!r}")
        if not 0 < self.clip_eps < 1:
            raise ConfigError(f"config key {where}.clip_eps: expected a number in (0, 1), found {self.clip_eps!r}")

    def architecture(self) -> dict:
        """The values of :data:`ARCHITECTURE_KEYS`."""
        return {k: getattr(self, k) for k in ARCHITECTURE_KEYS}
