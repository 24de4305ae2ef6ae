"""GA-MATR's settings (config.yaml ``methods.ga_matr``, one profile's budget merged in)."""
from __future__ import annotations

import dataclasses

from dswm.config import ENUM, ConfigError, check_fields, setting
from dswm.methods.matmul import MatmulDtype

ARCHITECTURE_KEYS = ("crop_radius", "context_side", "d_model", "heads", "layers", "ffn_hidden", "critic_hidden",
                     "critic_depth")
"""The settings that shape the networks: a model file is loaded only under the same values."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class GAMATRSettings:
    """Networks, HAPPO optimization, fairness term and budget of GA-MATR (all of them shape training)."""

    crop_radius: int = setting("natural")
    """Half-width in cells of a UAV token's local crop of the w+1 log1p demand maps ((2 r + 1)^2 cells)."""
    context_side: int = setting("count")
    """The demand maps are pooled (mean and max) to a P x P grid: P^2 demand-context tokens."""
    d_model: int = setting("count")
    """Width of every token (UAV and demand context)."""
    heads: int = setting("count")
    """Attention heads of each attention layer; must divide d_model."""
    layers: int = setting("count")
    """Graph-attention blocks: masked self-attention among UAVs, cross-attention to the context, feed-forward."""
    ffn_hidden: int = setting("count")
    """Hidden width of each block's feed-forward layer."""
    critic_hidden: int = setting("count")
    """Width of the centralized critic's hidden layers."""
    critic_depth: int = setting("count")
    """Hidden layers of the centralized critic (the first reads the flat global observation)."""
    actor_lr: float = setting("positive")
    """Adam learning rate of the policy (every agent's sequential step)."""
    critic_lr: float = setting("positive")
    """Adam learning rate of the critic."""
    gamma: float = setting("below_one")
    """Discount per slot."""
    gae_lambda: float = setting("fraction")
    """GAE lambda."""
    clip_eps: float = setting("open_fraction")
    """PPO clip: each agent's ratio is clipped to [1 - eps, 1 + eps] in its surrogate."""
    epochs: int = setting("count")
    """Passes over a rollout by EACH agent's sequential update (HAPPO's ppo_epoch)."""
    critic_epochs: int = setting("count")
    """Passes over a rollout by the critic."""
    minibatches: int = setting("count")
    """Minibatches per pass (of both the agents' and the critic's updates)."""
    entropy_coef: float = setting("nonnegative")
    """Weight of the updated agent's Gaussian entropy in its loss."""
    init_std: float = setting("positive")
    """Initial std of every agent's Gaussian (state-independent, learned per agent and action component)."""
    max_grad_norm: float = setting("positive")
    """Largest gradient norm of each optimizer step."""
    fairness_weight: float = setting("nonnegative")
    """Weight of the load-imbalance term (std / mean of the available UAVs' served load) taken off the learner's
    reward each slot; evaluation scores the environment's reward."""
    n_envs: int = setting("count")
    """Training days stepped together in one rollout (one round; its update follows)."""
    matmul_dtype: MatmulDtype = setting(ENUM)
    """The number format of the policy's matrix products (:mod:`dswm.methods.matmul`'s names): ``bfloat16`` runs its
    tokens and graph-attention blocks under torch's autocast (products in bfloat16 with float32 accumulation; the
    residual stream, the layer norms, the softmax, the heads, the critic, the weights and Adam's state float32)."""
    transitions: int = setting("count")
    """Environment transitions in all: whole rounds, a multiple of n_envs x (slots_per_day - 1)."""
    log_points: int = setting("count")
    """Most entries of the training history (each the mean over a window of rounds)."""
    checkpoint_every: int = setting("count")
    """Rounds between two checkpoints (one is also written at the end)."""

    def __post_init__(self):
        where = "methods.ga_matr"
        check_fields(self, where)
        if self.d_model % self.heads:
            raise ConfigError(f"config key {where}.heads: expected a divisor of d_model = {self.d_model}, "
                              f"found {self.heads}")

    def architecture(self) -> dict:
        """The values of :data:`ARCHITECTURE_KEYS`."""
        return {k: getattr(self, k) for k in ARCHITECTURE_KEYS}
