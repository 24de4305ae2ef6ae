"""SB3's SAC with a leaner gradient step: the same algorithm, losses, order of updates and random draws.

:class:`SAC` subclasses ``stable_baselines3.SAC`` (its name is kept: model files say ``"algorithm": "SAC"``) and
changes only how a gradient step is computed, at the paper's sizes a 2,914-wide input and two [256, 256] critics:

* the critics' parameters are frozen while the actor's loss is differentiated: SB3 computes their gradients
  there too and throws them away at the next critic step (the most expensive part of that backward pass);
* every Linear layer computes its product in ``matmul_dtype`` (:mod:`dswm.methods.matmul`); the critics'
  input [s, a] is built once per evaluation in that dtype (the actor reads float32 observations: SB3's
  preprocessing would convert them back);
* (set by ``SACController`` through SB3's ``optimizer_kwargs``) the actor's and the critics' optimizers are
  torch's fused Adam (``fused=True``: one pass over the parameters instead of a dozen; the same update up to
  rounding);
* the Polyak step of the target critics is one ``torch._foreach`` call per operation (SB3's arithmetic:
  target * (1 - tau) + tau * param, bit for bit);
* the replay buffer hands its sampled rows to torch without a second copy (:class:`ReplayBuffer`).

With ``matmul_dtype="float32"`` and the same optimizer a step is SB3's bit for bit (tests/test_rl_sb3.py).
"""
from __future__ import annotations

import numpy as np
import stable_baselines3
import torch
from stable_baselines3.common.buffers import ReplayBuffer as SB3ReplayBuffer
from stable_baselines3.common.utils import polyak_update
from torch.nn import functional as F

from dswm.methods.matmul import MATMUL_DTYPES, set_matmul_dtype


class ReplayBuffer(SB3ReplayBuffer):
    """SB3's replay buffer; a sample's arrays (fresh copies made by numpy's indexing) become tensors in place."""

    def to_torch(self, array: np.ndarray, copy: bool = True) -> torch.Tensor:
        return torch.as_tensor(array, device=self.device)


class SAC(stable_baselines3.SAC):
    """``stable_baselines3.SAC`` with the gradient step of the module's docstring.

    Args:
        matmul_dtype: the products' dtype, a key of ``dswm.methods.matmul.MATMUL_DTYPES`` (saved with the model).
        Other arguments: SB3's.
    """

    def __init__(self, *args, matmul_dtype: str = "float32", **kwargs):
        self.matmul_dtype = matmul_dtype
        super().__init__(*args, **kwargs)

    def _setup_model(self) -> None:
        super()._setup_model()
        set_matmul_dtype(self.policy, self.matmul_dtype)
        self._critic_params = list(self.critic.parameters())
        self._target_params = list(self.critic_target.parameters())

    def _excluded_save_params(self) -> list[str]:
        return super()._excluded_save_params() + ["_critic_params", "_target_params"]

    def _q(self, critic, features: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """(N, n_critics) Q(s, a) of ``critic``'s networks on ``features`` (the flat observations, already in the
        products' dtype) and ``actions``: SB3's ``ContinuousCritic.forward`` with the input [s, a] built once in
        that dtype."""
        x = torch.cat([features, actions.to(features.dtype)], dim=1)
        return torch.cat([q_net(x) for q_net in critic.q_networks], dim=1)

    def _polyak(self) -> None:
        with torch.no_grad():
            torch._foreach_mul_(self._target_params, 1 - self.tau)
            torch._foreach_add_(self._target_params, self._critic_params, alpha=self.tau)

    def train(self, gradient_steps: int, batch_size: int = 64) -> None:
        """SB3's ``SAC.train`` step for step (sampling, entropy coefficient, critic, actor, targets)."""
        self.policy.set_training_mode(True)
        optimizers = [self.actor.optimizer, self.critic.optimizer]
        if self.ent_coef_optimizer is not None:
            optimizers += [self.ent_coef_optimizer]
        self._update_learning_rate(optimizers)
        ent_coef_losses, ent_coefs, actor_losses, critic_losses = [], [], [], []
        dtype = MATMUL_DTYPES[self.matmul_dtype]
        for gradient_step in range(gradient_steps):
            replay_data = self.replay_buffer.sample(batch_size, env=self._vec_normalize_env)
            # The critics' observations in the products' dtype
            obs, next_obs = replay_data.observations.to(dtype), replay_data.next_observations.to(dtype)
            discounts = replay_data.discounts if replay_data.discounts is not None else self.gamma
            if self.use_sde:
                self.actor.reset_noise()
            # Action by the current actor for the sampled state
            actions_pi, log_prob = self.actor.action_log_prob(replay_data.observations)
            log_prob = log_prob.reshape(-1, 1)
            # Entropy coefficient
            ent_coef_loss = None
            if self.ent_coef_optimizer is not None and self.log_ent_coef is not None:
                ent_coef = torch.exp(self.log_ent_coef.detach())
                ent_coef_loss = -(self.log_ent_coef * (log_prob + self.target_entropy).detach()).mean()
                ent_coef_losses.append(ent_coef_loss.item())
            else:
                ent_coef = self.ent_coef_tensor
            ent_coefs.append(ent_coef.item())
            if ent_coef_loss is not None and self.ent_coef_optimizer is not None:
                self.ent_coef_optimizer.zero_grad()
                ent_coef_loss.backward()
                self.ent_coef_optimizer.step()
            # Critic: TD target from the target critics, the actor's next action and its entropy
            with torch.no_grad():
                next_actions, next_log_prob = self.actor.action_log_prob(replay_data.next_observations)
                next_q_values = self._q(self.critic_target, next_obs, next_actions)
                next_q_values, _ = torch.min(next_q_values, dim=1, keepdim=True)
                next_q_values = next_q_values - ent_coef * next_log_prob.reshape(-1, 1)
                target_q_values = replay_data.rewards + (1 - replay_data.dones) * discounts * next_q_values
            current_q_values = self._q(self.critic, obs, replay_data.actions).split(1, dim=1)
            critic_loss = 0.5 * sum(F.mse_loss(current_q, target_q_values) for current_q in current_q_values)
            critic_losses.append(critic_loss.item())
            self.critic.optimizer.zero_grad()
            critic_loss.backward()
            self.critic.optimizer.step()
            # Actor: through the updated critics, whose parameters get no gradient here
            self.critic.requires_grad_(False)
            min_qf_pi, _ = torch.min(self._q(self.critic, obs, actions_pi), dim=1, keepdim=True)
            actor_loss = (ent_coef * log_prob - min_qf_pi).mean()
            actor_losses.append(actor_loss.item())
            self.actor.optimizer.zero_grad()
            actor_loss.backward()
            self.critic.requires_grad_(True)
            self.actor.optimizer.step()
            # Targets
            if gradient_step % self.target_update_interval == 0:
                self._polyak()
                polyak_update(self.batch_norm_stats, self.batch_norm_stats_target, 1.0)
        self._n_updates += gradient_steps
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/ent_coef", np.mean(ent_coefs))
        self.logger.record("train/actor_loss", np.mean(actor_losses))
        self.logger.record("train/critic_loss", np.mean(critic_losses))
        if len(ent_coef_losses) > 0:
            self.logger.record("train/ent_coef_loss", np.mean(ent_coef_losses))
