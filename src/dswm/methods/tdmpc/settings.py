"""TD-MPC's typed settings (config.yaml ``methods.tdmpc``, its ``budgets.<profile>`` merged over it).

The pre-collection (``methods.tdmpc.precollect``, :class:`PreCollect`) runs the collection DSWM's world model starts
from too (``dswm.methods.collect``); its values equal ``dswm.training``'s and ``dswm.budgets.<profile>.transitions``
by choice, so TD-MPC starts from the very transitions DSWM pre-collects with the same seed, but they are TD-MPC's own
keys: changing DSWM's budget does not change TD-MPC's.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Literal, Mapping

from dswm.config import ConfigError, build, with_budget
from dswm.methods.collect import CollectSettings
from dswm.methods.tdmpc.planner import MPPIConfig


@dataclasses.dataclass(frozen=True, kw_only=True)
class PreCollect(CollectSettings):
    """TD-MPC's pre-collection (config.yaml ``methods.tdmpc.precollect``): the collection's settings and its size."""

    transitions: int
    """Decisions pre-collected, rounded up to whole days."""

    def __post_init__(self):
        if self.transitions < 1:
            raise ConfigError(f"config key methods.tdmpc.precollect.transitions: expected an integer >= 1, found "
                              f"{self.transitions}")
        super().__post_init__()


@dataclasses.dataclass(frozen=True, kw_only=True)
class TDMPCSettings:
    """TD-MPC's settings (config.yaml ``methods.tdmpc``; values and reasons there)."""

    # ---- TOLD
    latent: int
    """Size of the latent state z."""
    hidden: int
    """Width of every MLP (dynamics, reward, twin Q, policy, the encoder's head)."""
    enc_channels: int
    """Channels of the encoder's first conv (the second has twice as many)."""
    # ---- planning (MPPI) and the TD horizon
    horizon: int
    """H: slots of the latent rollout, in training (the consistency/reward/value horizon) and in planning."""
    n_samples: int
    """Action sequences sampled from the Gaussian per iteration."""
    policy_share: float
    """Extra sequences rolled out by the policy prior, as a fraction of ``n_samples`` (TD-MPC: 24 of 512)."""
    n_elites: int
    """Sequences that refit the Gaussian."""
    iterations: int
    """Refits per slot."""
    temperature: float
    """Elite weights exp(temperature (G - max G)), as in TD-MPC: larger values concentrate them."""
    momentum: float
    """Share of the previous iteration's mean kept in each refit."""
    min_std: float
    """Floor of the refitted std; also the noise of the policy's sequences."""
    max_std: float
    """Initial std of every slot's Gaussian and the ceiling of the refitted one."""
    # ---- losses and optimization
    gamma: float
    """Discount of returns and TD targets."""
    rho: float
    """Weight rho^t of the rollout's step t in every loss."""
    tau: float
    """Polyak rate of the target network after every gradient step."""
    consistency_coef: float
    """Weight of the latent-consistency loss."""
    reward_coef: float
    """Weight of the reward loss."""
    value_coef: float
    """Weight of the TD value loss."""
    lr: float
    """Adam learning rate of the encoder, dynamics, reward and Q."""
    pi_lr: float
    """Adam learning rate of the policy."""
    grad_clip: float
    """Global gradient-norm clip of each update."""
    batch: int
    """Sequences of H+1 observations per gradient step."""
    # ---- budgets
    steps: int
    """Gradient steps in all."""
    seed_steps: int
    """Of ``steps``, those taken on the pre-collected transitions before the first own episode."""
    episodes: int
    """Own-interaction day-episodes on TRAINING days (0: the pre-collection only)."""
    parallel: int
    """Training days played together per interaction round."""
    explore: Literal["mppi", "policy"]
    """Own-interaction behaviour: MPPI with its final std as noise (TD-MPC), or the policy plus noise."""
    explore_std: float
    """Noise std of ``explore: policy``."""
    log_points: int
    """Points of the loss history (averages over equal windows of steps)."""
    checkpoint_every: int
    """Gradient steps between complete checkpoints (every round's end and the last step write one too)."""
    precollect: PreCollect
    """The pre-collected transitions the training starts from."""

    def __post_init__(self):
        counts = ("latent", "hidden", "enc_channels", "horizon", "n_samples", "n_elites", "iterations", "batch",
                  "steps", "parallel", "log_points", "checkpoint_every")
        bad = [n for n in counts if getattr(self, n) < 1]
        bad += [n for n in ("seed_steps", "episodes") if getattr(self, n) < 0]
        bad += [n for n in ("temperature", "lr", "pi_lr", "grad_clip", "max_std", "consistency_coef")
                if getattr(self, n) <= 0]
        bad += [n for n in ("reward_coef", "value_coef", "explore_std", "policy_share") if getattr(self, n) < 0]
        bad += [n for n in ("gamma", "rho", "tau") if not 0.0 < getattr(self, n) <= 1.0]
        bad += [n for n in ("momentum",) if not 0.0 <= self.momentum < 1.0]
        bad += [n for n in ("min_std",) if not 0.0 <= self.min_std <= self.max_std]
        if self.n_elites > self.n_samples:
            bad.append("n_elites")
        if self.seed_steps > self.steps or (self.episodes > 0 and self.seed_steps == self.steps):
            bad.append("seed_steps")
        if bad:
            raise ConfigError(f"config key methods.tdmpc: expected sizes >= 1, rates and coefficients > 0, gamma, rho "
                              f"and tau in (0, 1], momentum in [0, 1), 0 <= min_std <= max_std, n_elites <= "
                              f"n_samples and seed_steps < steps when there are episodes; found "
                              f"{ {n: getattr(self, n) for n in sorted(set(bad))} }")

    @property
    def n_policy(self) -> int:
        """Sequences rolled out by the policy per iteration."""
        return int(round(self.policy_share * self.n_samples))

    def mppi(self) -> MPPIConfig:
        """The planner's settings."""
        return MPPIConfig(horizon=self.horizon, n_samples=self.n_samples, n_policy=self.n_policy,
                          n_elites=self.n_elites, iterations=self.iterations, temperature=self.temperature,
                          momentum=self.momentum, min_std=self.min_std, max_std=self.max_std, gamma=self.gamma)


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
