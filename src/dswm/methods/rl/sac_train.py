"""SB3's SAC with a leaner gradient step: the same algorithm, losses, order of updates and random draws.

:class:`SAC` subclasses ``stable_baselines3.SAC`` (its name is kept: model files say ``"algorithm": "SAC"``) and
changes only how a gradient step is computed, at the paper's sizes a 2,914-wide input and two [256, 256] critics:

* the critics' parameters are frozen while the actor's loss is differentiated: SB3 computes their gradients
  there too and throws them away at the next critic step (the most expensive part of that backward pass);
* every Linear layer computes its product in ``matmul_dtype`` (:mod:`dswm.methods.matmul`). With bfloat16:
  the replay buffer stores the observations already rounded to bfloat16 (every product that reads them rounds
  them so; half the memory), and the actor and the critics read them as they are (SB3's preprocessing would
  convert them to float32 and back); each layer rounds its weight once after each change of it instead of
  once per use; the critics' first layer takes [s, a] as the fixed observation beside the action, so the
  actor's loss computes no gradient for the observation's columns. The values are those of the plain
  bfloat16 step (tests/test_rl_sb3.py);
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
from stable_baselines3.sac.policies import LOG_STD_MAX, LOG_STD_MIN
from torch.nn import functional as F

from dswm.methods.matmul import MATMUL_DTYPES, forget_casts, keep_casts, set_matmul_dtype


class ReplayBuffer(SB3ReplayBuffer):
    """SB3's replay buffer; a sample's arrays (fresh copies made by numpy's indexing) become tensors in place.

    Args:
        observation_dtype: ``"float32"`` (SB3's) or ``"bfloat16"``: the observations (and next observations) are
            stored rounded to bfloat16 (their bits in a uint16 array; torch's rounding, to nearest even) and
            sampled as bfloat16 tensors.
        Other arguments: SB3's.
    """

    def __init__(self, *args, observation_dtype: str = "float32", **kwargs):
        super().__init__(*args, **kwargs)
        if observation_dtype not in MATMUL_DTYPES:
            raise ValueError(f"observation_dtype: expected one of {sorted(MATMUL_DTYPES)}, found {observation_dtype!r}")
        if observation_dtype == "bfloat16":  # the arrays' dtype says how they are stored (_stored, to_torch)
            self.observations = np.zeros(self.observations.shape, dtype=np.uint16)
            if not self.optimize_memory_usage:
                self.next_observations = np.zeros(self.next_observations.shape, dtype=np.uint16)

    def _stored(self, obs: np.ndarray) -> np.ndarray:
        if self.observations.dtype != np.uint16:
            return obs
        t = torch.from_numpy(np.ascontiguousarray(obs, dtype=np.float32)).to(torch.bfloat16)
        return t.view(torch.int16).numpy().view(np.uint16)

    def add(self, obs, next_obs, action, reward, done, infos) -> None:
        super().add(self._stored(obs), self._stored(next_obs), action, reward, done, infos)

    def to_torch(self, array: np.ndarray, copy: bool = True) -> torch.Tensor:
        if array.dtype == np.uint16:  # stored observations: bfloat16 bits
            return torch.from_numpy(array).view(torch.bfloat16).to(self.device)
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
        that dtype; in bfloat16 each network's first layer passes a gradient to the action's columns only
        (``MatmulLinear.forward_tail``)."""
        if self.matmul_dtype == "float32":
            x = torch.cat([features, actions], dim=1)
            return torch.cat([q_net(x) for q_net in critic.q_networks], dim=1)
        x = torch.cat([features, actions.detach().to(features.dtype)], dim=1)
        return torch.cat([q_net[1:](q_net[0].forward_tail(x, actions)) for q_net in critic.q_networks], dim=1)

    def _actor_log_prob(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """SB3's ``actor.action_log_prob(obs)`` on observations as sampled (bfloat16 ones are not converted to
        float32 first: the first product rounds its input to bfloat16 anyway)."""
        actor = self.actor
        if obs.dtype == torch.float32 or actor.use_sde:  # gSDE's noise needs SB3's own path
            return actor.action_log_prob(obs)
        latent_pi = actor.latent_pi(actor.features_extractor(obs))
        log_std = torch.clamp(actor.log_std(latent_pi), LOG_STD_MIN, LOG_STD_MAX)
        return actor.action_dist.log_prob_from_params(actor.mu(latent_pi), log_std)

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
        keep_casts(self.policy, True)
        try:
            ent_coef_losses, ent_coefs, actor_losses, critic_losses = self._train_steps(gradient_steps, batch_size)
        finally:
            keep_casts(self.policy, False)
        self._n_updates += gradient_steps
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/ent_coef", np.mean(ent_coefs))
        self.logger.record("train/actor_loss", np.mean(actor_losses))
        self.logger.record("train/critic_loss", np.mean(critic_losses))
        if len(ent_coef_losses) > 0:
            self.logger.record("train/ent_coef_loss", np.mean(ent_coef_losses))

    def _train_steps(self, gradient_steps: int, batch_size: int) -> tuple[list, list, list, list]:
        """``gradient_steps`` of SB3's step; each step's entropy-coefficient loss (with a learned coefficient),
        coefficient, actor loss and critic loss, in four lists."""
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
            actions_pi, log_prob = self._actor_log_prob(replay_data.observations)
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
                next_actions, next_log_prob = self._actor_log_prob(replay_data.next_observations)
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
            forget_casts(self.critic)
            # Actor: through the updated critics, whose parameters get no gradient here
            self.critic.requires_grad_(False)
            min_qf_pi, _ = torch.min(self._q(self.critic, obs, actions_pi), dim=1, keepdim=True)
            actor_loss = (ent_coef * log_prob - min_qf_pi).mean()
            actor_losses.append(actor_loss.item())
            self.actor.optimizer.zero_grad()
            actor_loss.backward()
            self.critic.requires_grad_(True)
            self.actor.optimizer.step()
            forget_casts(self.actor)
            # Targets
            if gradient_step % self.target_update_interval == 0:
                self._polyak()
                forget_casts(self.critic_target)
                polyak_update(self.batch_norm_stats, self.batch_norm_stats_target, 1.0)
        return ent_coef_losses, ent_coefs, actor_losses, critic_losses
