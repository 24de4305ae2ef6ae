"""What the project's Stable-Baselines3 learners share: the SB3 methods (``ppo``, ``sac``; :mod:`.sb3`) and
EMORL-TCTO's inner PPO learner (``dswm.methods.emorl_tcto``).

* :class:`SB3Params`: the network and optimizer keys of every SB3 learner; :class:`PPOParams`: PPO's
  hyper-parameters on top, their checks and SB3's ``PPO`` keyword arguments from them. Each method's settings
  subclass these and are read from its own config section (``methods.ppo``, ``methods.emorl_tcto``).
* :class:`DumpEachUpdate`: dumps SB3's logger after every update, so a history averages every update's losses.
* :func:`rng_states` / :func:`set_rng_states`: the RNG states a checkpoint keeps and restores.
"""
from __future__ import annotations

import dataclasses
import random
from typing import Any, ClassVar, Mapping

import numpy as np
import torch
from stable_baselines3.common.base_class import BaseAlgorithm
from stable_baselines3.common.callbacks import BaseCallback

from dswm.config import ConfigError, check_fields, setting


# ---- settings --------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True, kw_only=True)
class SB3Params:
    """The network and optimizer of an SB3 learner (a subclass names its config section in ``section``)."""

    section: ClassVar[str] = "methods"

    n_envs: int = setting("count")
    """Training days stepped together by one core call; a round is n_envs day-episodes."""
    net_arch: tuple[int, ...] = setting("net_arch")
    """Hidden-layer widths of the actor's MLP and of each critic's (separate networks)."""
    learning_rate: float = setting("positive")
    """Adam's learning rate (constant) of every network."""
    gamma: float = setting("discount")
    """Discount per slot."""
    batch_size: int = setting("count")
    """Minibatch size of a gradient step."""

    def _fail(self, key: str, expected: str) -> None:
        raise ConfigError(f"config key {self.section}.{key}: expected {expected}, found {getattr(self, key)!r}")

    def __post_init__(self):
        check_fields(self, self.section)  # every field's, a subclass's included


@dataclasses.dataclass(frozen=True, kw_only=True)
class PPOParams(SB3Params):
    """SB3 PPO's hyper-parameters: one rollout is one round, n_envs x 143 transitions; batch_size divides it."""

    n_epochs: int = setting("count")
    """Passes over each rollout."""
    gae_lambda: float = setting("fraction")
    """GAE's lambda."""
    clip_range: float = setting("positive")
    """PPO's ratio clipping."""
    ent_coef: float = setting("nonnegative")
    """Weight of the entropy bonus."""
    vf_coef: float = setting("positive")
    """Weight of the value loss."""
    max_grad_norm: float = setting("positive")
    """Gradient-norm clipping."""
    log_std_init: float = setting("number")
    """Initial log std of the Gaussian policy (state-independent, learned)."""

    def rollout_check(self, horizon: int) -> None:
        """The check that needs the day's length: batch_size divides the rollout of n_envs x ``horizon``."""
        if (self.n_envs * horizon) % self.batch_size:
            raise ConfigError(f"config key {self.section}.batch_size: expected a divisor of the rollout n_envs x "
                              f"{horizon} = {self.n_envs * horizon}, found {self.batch_size}")

    def ppo_kwargs(self, horizon: int) -> dict:
        """SB3 ``PPO`` keyword arguments (``horizon``: decisions per day, the rollout's length per environment)."""
        arch = list(self.net_arch)
        return {"learning_rate": self.learning_rate, "n_steps": horizon, "batch_size": self.batch_size,
                "n_epochs": self.n_epochs, "gamma": self.gamma, "gae_lambda": self.gae_lambda,
                "clip_range": self.clip_range, "ent_coef": self.ent_coef, "vf_coef": self.vf_coef,
                "max_grad_norm": self.max_grad_norm,
                "policy_kwargs": {"net_arch": {"pi": arch, "vf": list(arch)}, "log_std_init": self.log_std_init}}


# ---- training helpers ------------------------------------------------------------------------------------
def rng_states(model: BaseAlgorithm) -> dict:
    """The python, numpy, torch (and CUDA) RNG states and the action space's, for a checkpoint."""
    return {"python": random.getstate(), "numpy": np.random.get_state(), "torch": torch.get_rng_state(),
            "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None,
            "action_space": model.action_space.np_random.bit_generator.state}


def set_rng_states(model: BaseAlgorithm, states: Mapping[str, Any]) -> None:
    """Restore what :func:`rng_states` returned."""
    random.setstate(states["python"])
    np.random.set_state(states["numpy"])
    torch.set_rng_state(states["torch"])
    if states.get("cuda") is not None and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(states["cuda"])
    model.action_space.np_random.bit_generator.state = states["action_space"]


class DumpEachUpdate(BaseCallback):
    """Dumps SB3's logger after every update, so the history averages every update's losses."""

    def __init__(self, n_updates: int):
        super().__init__(verbose=0)
        self.seen = n_updates

    def flush(self, model: BaseAlgorithm) -> None:
        if model._n_updates != self.seen:
            model.logger.dump(model.num_timesteps)
            self.seen = model._n_updates

    def _on_step(self) -> bool:
        self.flush(self.model)
        return True
