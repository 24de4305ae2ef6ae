"""TD-MPC's typed settings (config.yaml ``methods.tdmpc``, its ``budgets.<profile>`` merged over it).

The pre-collection (``methods.tdmpc.precollect``, :class:`PreCollect`) runs the collection DSWM's world model starts
from too (``dswm.methods.collect``); its values equal ``dswm.training``'s and ``dswm.budgets.<profile>.transitions``
by choice, so TD-MPC starts from the very transitions DSWM pre-collects with the same seed, but they are TD-MPC's own
keys: changing DSWM's budget does not change TD-MPC's.
"""
from __future__ import annotations

import dataclasses
from typing import Any, ClassVar, Literal, Mapping

from dswm.config import ENUM, SECTION, ConfigError, build, check_fields, setting, with_budget
from dswm.methods.collect import CollectSettings
from dswm.methods.matmul import MatmulDtype
from dswm.methods.tdmpc.planner import MPPIConfig


@dataclasses.dataclass(frozen=True, kw_only=True)
class PreCollect(CollectSettings):
    """TD-MPC's pre-collection (config.yaml ``methods.tdmpc.precollect``): the collection's settings and its size."""

    section: ClassVar[str] = "methods.tdmpc.precollect"

    transitions: int = setting("count")
    """Decisions pre-collected, rounded up to whole days."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class TDMPCSettings:
    """TD-MPC's settings (config.yaml ``methods.tdmpc``; values and reasons there)."""

    # ---- TOLD
    latent: int = setting("count")
    """Size of the latent state z."""
    hidden: int = setting("count")
    """Width of every MLP (dynamics, reward, twin Q, policy, the encoder's head)."""
    enc_channels: int = setting("count")
    """Channels of the encoder's first conv (the second has twice as many)."""
    # ---- planning (MPPI) and the TD horizon
    horizon: int = setting("count")
    """H: slots of the latent rollout, in training (the consistency/reward/value horizon) and in planning."""
    n_samples: int = setting("count")
    """Action sequences sampled from the Gaussian per iteration."""
    policy_share: float = setting("nonnegative")
    """Extra sequences rolled out by the policy prior, as a fraction of ``n_samples`` (TD-MPC: 24 of 512)."""
    n_elites: int = setting("count")
    """Sequences that refit the Gaussian."""
    iterations: int = setting("count")
    """Refits per slot."""
    temperature: float = setting("positive")
    """Elite weights exp(temperature (G - max G)), as in TD-MPC: larger values concentrate them."""
    momentum: float = setting("below_one")
    """Share of the previous iteration's mean kept in each refit."""
    min_std: float = setting("nonnegative")
    """Floor of the refitted std; also the noise of the policy's sequences."""
    max_std: float = setting("positive")
    """Initial std of every slot's Gaussian and the ceiling of the refitted one."""
    # ---- losses and optimization
    gamma: float = setting("discount")
    """Discount of returns and TD targets."""
    rho: float = setting("discount")
    """Weight rho^t of the rollout's step t in every loss."""
    tau: float = setting("discount")
    """Polyak rate of the target network after every gradient step."""
    consistency_coef: float = setting("positive")
    """Weight of the latent-consistency loss."""
    reward_coef: float = setting("nonnegative")
    """Weight of the reward loss."""
    value_coef: float = setting("nonnegative")
    """Weight of the TD value loss."""
    lr: float = setting("positive")
    """Adam learning rate of the encoder, dynamics, reward and Q."""
    pi_lr: float = setting("positive")
    """Adam learning rate of the policy."""
    grad_clip: float = setting("positive")
    """Global gradient-norm clip of each update."""
    batch: int = setting("count")
    """Sequences of H+1 observations per gradient step."""
    matmul_dtype: MatmulDtype = setting(ENUM)
    """The number format of the gradient step's matrix products and convolutions (:mod:`dswm.methods.matmul`'s
    names): ``bfloat16`` runs the losses' forward under torch's autocast (float32 weights, Adam state and loss sums),
    and MPPI's latent rollouts too (:mod:`dswm.methods.tdmpc.planner`: rewards and values summed in float32)."""
    # ---- budgets
    steps: int = setting("count")
    """Gradient steps in all."""
    seed_steps: int = setting("natural")
    """Of ``steps``, those taken on the pre-collected transitions before the first own episode."""
    episodes: int = setting("natural")
    """Own-interaction day-episodes on TRAINING days (0: the pre-collection only)."""
    parallel: int = setting("count")
    """Training days played together per interaction round."""
    explore: Literal["mppi", "policy"] = setting(ENUM)
    """Own-interaction behaviour: MPPI with its final std as noise (TD-MPC), or the policy plus noise."""
    explore_std: float = setting("nonnegative")
    """Noise std of ``explore: policy``."""
    log_points: int = setting("count")
    """Points of the loss history (averages over equal windows of steps)."""
    checkpoint_every: int = setting("count")
    """Gradient steps between complete checkpoints (every round's end and the last step write one too)."""
    precollect: PreCollect = setting(SECTION)
    """The pre-collected transitions the training starts from."""

    def __post_init__(self):
        check_fields(self, "methods.tdmpc")
        wrong = {"min_std": self.min_std > self.max_std, "n_elites": self.n_elites > self.n_samples,
                 "seed_steps": self.seed_steps > self.steps or (self.episodes > 0 and self.seed_steps == self.steps)}
        bad = [n for n, w in wrong.items() if w]
        if bad:
            raise ConfigError(f"config key methods.tdmpc: expected min_std <= max_std, n_elites <= n_samples and "
                              f"seed_steps < steps when there are episodes; found "
                              f"{ {n: getattr(self, n) for n in bad} }")

    @property
    def n_policy(self) -> int:
        """Sequences rolled out by the policy per iteration."""
        return int(round(self.policy_share * self.n_samples))

    def mppi(self) -> MPPIConfig:
        """The planner's settings."""
        return MPPIConfig(horizon=self.horizon, n_samples=self.n_samples, n_policy=self.n_policy,
                          n_elites=self.n_elites, iterations=self.iterations, temperature=self.temperature,
                          momentum=self.momentum, min_std=self.min_std, max_std=self.max_std, gamma=self.gamma,
                          matmul_dtype=self.matmul_dtype)


def resolve(config: Mapping[str, Any], *, name: str = "tdmpc", profile: str) -> TDMPCSettings:
    """``methods.<name>`` merged with its ``budgets.<profile>`` (mappings key by key, so a budget may set
    ``precollect.transitions`` alone).

    Raises:
        ConfigError: a missing section, an unknown, missing or mistyped key, or a value out of range.
    """
    where = f"methods.{name}"
    section = config["methods"].get(name)
    if not isinstance(section, Mapping):
        raise ConfigError(f"config.yaml: key '{where}' must be a mapping of TD-MPC's settings; found {section!r}")
    return build(TDMPCSettings, *with_budget(section, profile, where))
