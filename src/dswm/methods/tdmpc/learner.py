"""TD-MPC's losses and gradient step (Hansen et al. 2022, Algorithm 1's update).

For a window of H+1 observations o_0..o_H, actions a_0..a_{H-1} and rewards r_0..r_{H-1} of one day:
    z_0 = h(o_0);  z_{t+1}, r_hat_t = d(z_t, a_t), R(z_t, a_t)
    consistency  sum_t rho^t mean_j (z_{t+1} - sg[h'(o_{t+1})])_j^2          (target encoder h', stop-gradient)
    reward       sum_t rho^t (r_hat_t - r_t)^2
    value        sum_t rho^t sum_i (Q_i(z_t, a_t) - y_t)^2,   y_t = r_t + gamma (1 - term_t) min_i Q'_i(z', pi(z'))
                 with z' = h'(o_{t+1}) and the target network's twin Q'
    policy       sum_t rho^t -min_i Q_i(sg[z_t], pi(sg[z_t])) / sum_t rho^t   (only the policy is updated)
The TOLD loss (consistency, reward and value, weighted) is divided by H as in TD-MPC; after each step the target
network moves towards the online one by Polyak averaging (``tau``). The environment never terminates (a day's
end TRUNCATES), so term_t is always 0 and every target bootstraps, the day's last transition included.

``matmul_dtype: bfloat16`` runs the forward passes of both losses under torch's autocast: convolutions and matrix
products in bfloat16 (float32 accumulation), the activations between them in bfloat16; every network output is
taken back to float32 before it enters a loss, so the loss sums, the gradients as stored, the weights and Adam's
state stay float32. ``float32`` leaves every operation as it was.
"""
from __future__ import annotations

import copy

import torch
from torch import nn

from dswm.methods.matmul import MATMUL_DTYPES, autocast
from dswm.methods.tdmpc.model import TOLD
from dswm.methods.tdmpc.settings import TDMPCSettings

METRICS = ("total", "consistency", "reward", "value", "pi", "td_target")
"""Names of the per-step metrics (``losses/<name>`` in the history; ``td_target`` is the mean TD target y)."""


@torch.no_grad()
def polyak(target: nn.Module, online: nn.Module, tau: float) -> None:
    """theta' <- (1 - tau) theta' + tau theta, in place."""
    p_t, p_o = list(target.parameters()), [p.detach() for p in online.parameters()]
    if len(p_t) != len(p_o):
        raise ValueError(f"polyak: the target has {len(p_t)} parameters, the online network {len(p_o)}")
    torch._foreach_lerp_(p_t, p_o, tau)      # one call over all tensors: the same values as a loop of lerp_


class Learner:
    """The online TOLD, its target copy, both optimizers, the batch sampler's generator and the step count."""

    def __init__(self, model: TOLD, settings: TDMPCSettings, *, seed: int):
        self.model, self.s = model, settings
        self.target = copy.deepcopy(model).requires_grad_(False)
        self.optim = torch.optim.Adam(model.model_parameters(), lr=settings.lr)
        self.pi_optim = torch.optim.Adam(model.policy.parameters(), lr=settings.pi_lr)
        self.generator = torch.Generator().manual_seed(seed)
        self.step = 0

    @property
    def device(self) -> torch.device:
        return next(self.model.parameters()).device

    def autocast(self) -> torch.autocast:
        """The losses' forward in ``matmul_dtype`` (see the module docstring); disabled for float32."""
        return autocast(self.device.type, self.s.matmul_dtype)

    @torch.no_grad()
    def td_target(self, demand: torch.Tensor, fleet: torch.Tensor, time: torch.Tensor, reward: torch.Tensor,
                  terminated: torch.Tensor) -> torch.Tensor:
        """y = r + gamma (1 - terminated) min_i Q'_i(z', pi(z')), z' = h'(o') (target encoder and Q, online policy).

        Args: next observations with leading shape (...), reward (...), terminated (...) bool.  Returns: (...).
        """
        return self.bootstrap(self.target.encode(demand, fleet, time), reward, terminated)

    @torch.no_grad()
    def bootstrap(self, z_next: torch.Tensor, reward: torch.Tensor, terminated: torch.Tensor) -> torch.Tensor:
        """``td_target`` from the target encoder's latents z' = h'(o') (...,  latent) of the next observations."""
        q1, q2 = self.target.q(z_next, self.model.pi(z_next))
        return reward + self.s.gamma * (~terminated).to(reward.dtype) * torch.minimum(q1, q2).float()

    def losses(self, batch: dict[str, torch.Tensor]) -> tuple[torch.Tensor, list[torch.Tensor], dict[str, float]]:
        """The TOLD loss of one batch (``TransitionReplay.sample_windows``, its maps as ``demand`` or, scaled, as
        ``scaled_demand``), the rolled-out latents and metrics.

        Returns:
            (TOLD loss (scalar, divided by H), [z_0..z_H] each (B, latent), {metric: value}).
        """
        s, horizon = self.s, batch["action"].shape[0]
        scaled = "scaled_demand" in batch     # the replay's maps, scaled once (``sample_windows(scaled=True)``)
        demand = batch["scaled_demand" if scaled else "demand"]
        with self.autocast():     # .float(): each output in float32 (the same tensor when it is one already)
            with torch.no_grad():     # h'(o_1..o_H), once: the consistency targets and the TD targets' z'
                z_target = self.target.encode(demand[1:], batch["fleet"][1:], batch["time"][1:],
                                              scaled=scaled).float()
            y = self.bootstrap(z_target, batch["reward"], batch["terminated"])    # z_target: (H, B, latent)
            z = self.model.encode(demand[0], batch["fleet"][0], batch["time"][0], scaled=scaled).float()
            zs, cons, rew, val = [z], 0.0, 0.0, 0.0
            for t in range(horizon):
                w = s.rho ** t
                q1, q2 = (q.float() for q in self.model.q(z, batch["action"][t]))
                z, r_hat = (x.float() for x in self.model.next(z, batch["action"][t]))
                cons = cons + w * ((z - z_target[t]) ** 2).mean(-1)
                rew = rew + w * (r_hat - batch["reward"][t]) ** 2
                val = val + w * ((q1 - y[t]) ** 2 + (q2 - y[t]) ** 2)
                zs.append(z)
        cons, rew, val = cons.mean(), rew.mean(), val.mean()
        total = (s.consistency_coef * cons + s.reward_coef * rew + s.value_coef * val) / horizon
        values = torch.stack([total, cons, rew, val, y.mean()]).detach().tolist()   # one device read, not five
        return total, zs, dict(zip(("total", "consistency", "reward", "value", "td_target"), values))

    def policy_loss(self, zs: list[torch.Tensor]) -> torch.Tensor:
        """-min_i Q_i(z, pi(z)) on the detached latents, rho-weighted and normalized (Q frozen)."""
        loss, norm = 0.0, 0.0
        with self.autocast():
            for t, z in enumerate(zs):
                z = z.detach()
                q1, q2 = self.model.q(z, self.model.pi(z))
                loss = loss + self.s.rho ** t * -torch.minimum(q1, q2).float().mean()
                norm += self.s.rho ** t
        return loss / norm

    def update(self, batch: dict[str, torch.Tensor]) -> dict[str, float]:
        """One gradient step of the TOLD, one of the policy, then the Polyak update of the target."""
        batch = {k: v.to(self.device) for k, v in batch.items()}
        total, zs, metrics = self.losses(batch)
        self.optim.zero_grad(set_to_none=True)
        total.backward()
        nn.utils.clip_grad_norm_(self.model.model_parameters(), self.s.grad_clip)
        self.optim.step()
        # The policy's gradient alone (Q frozen): the backward pass stops at the policy's weights. The Q heads'
        # weights keep requires_grad, so autocast casts them once for the H+1 steps instead of once per step.
        pi_params = list(self.model.policy.parameters())
        pi_loss = self.policy_loss(zs)
        self.pi_optim.zero_grad(set_to_none=True)
        pi_loss.backward(inputs=pi_params)
        nn.utils.clip_grad_norm_(pi_params, self.s.grad_clip)
        self.pi_optim.step()
        polyak(self.target, self.model, self.s.tau)
        self.step += 1
        return {**metrics, "pi": pi_loss.item()}

    def train_step(self, replay) -> dict[str, float]:
        """Sample a batch from ``replay`` (``TransitionReplay``) and :meth:`update` on it."""
        return self.update(replay.sample_windows(self.s.batch, self.s.horizon, self.generator, scaled=True,
                                                 dtype=MATMUL_DTYPES[self.s.matmul_dtype]))

    def state_dict(self) -> dict:
        """Weights (online and target), optimizers, the sampler's generator and the step."""
        return {"model": self.model.state_dict(), "target": self.target.state_dict(),
                "optim": self.optim.state_dict(), "pi_optim": self.pi_optim.state_dict(),
                "sampler": self.generator.get_state(), "step": self.step}

    def load_state_dict(self, sd: dict) -> None:
        self.model.load_state_dict(sd["model"])
        self.target.load_state_dict(sd["target"])
        self.optim.load_state_dict(sd["optim"])
        self.pi_optim.load_state_dict(sd["pi_optim"])
        self.generator.set_state(sd["sampler"])
        self.step = int(sd["step"])
