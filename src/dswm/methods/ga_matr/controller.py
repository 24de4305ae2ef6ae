"""The GA-MATR controller: ``fit`` on the training core, then deterministic batched acting."""
from __future__ import annotations

from typing import Any, ClassVar, Mapping

import numpy as np
import torch

from dswm.methods.ga_matr.happo import Learner
from dswm.methods.ga_matr.networks import context_dim, policy_inputs, uav_dim
from dswm.methods.ga_matr.settings import GAMATRSettings
from dswm.methods.ga_matr.training import Trainer
from dswm.methods.rl.spaces import observation_dim
from dswm.methods.trained import TrainedController
from dswm.sim.core import Grid


class GAMATRController(TrainedController):
    """GA-MATR (Feng et al. 2024, re-implemented): a graph-attention policy shared by the UAVs, trained by HAPPO's
    sequential per-agent updates with a centralized critic and a load-fairness term in the learner's reward.

    ``act_batch`` runs the policy's mean (no sampling) on B days at once, the (B, K) UAVs in one pass, clipped to
    [-1, 1].
    """

    options_type: ClassVar[type] = GAMATRSettings
    model_label: ClassVar[str] = "GA-MATR"
    model_keys: ClassVar[tuple[str, ...]] = ("policy", "critic", "value_norm")

    def make_trainer(self, train_core) -> Trainer:
        return Trainer(core=train_core, settings=self.settings, seed=self.seed, device=self.device)

    def model_state(self) -> dict:
        """Policy and critic weights and the value normalizer."""
        net = self.learner
        return {"policy": net.policy.state_dict(), "critic": net.critic.state_dict(),
                "value_norm": net.value_norm.state_dict()}

    def build_learner(self, grid: Grid, scenario, blob: Mapping[str, Any]) -> Learner:
        maps = scenario.obs_window + 1
        learner = Learner(settings=self.settings, n_agents=scenario.n_uavs,
                          uav_in=uav_dim(maps, self.settings.crop_radius), context_in=context_dim(maps),
                          obs_dim=observation_dim(grid.rows, grid.cols, scenario), device=self.device)
        learner.policy.load_state_dict(blob["policy"])
        learner.critic.load_state_dict(blob["critic"])
        learner.value_norm.load_state_dict(blob["value_norm"])
        return learner

    @torch.no_grad()
    def act_batch(self, obs: Mapping[str, Any]) -> np.ndarray:
        """(B, K, 3) float32: the policy's mean actions, clipped to [-1, 1]."""
        x = policy_inputs(*self.observation_tensors(obs), radius=self.settings.crop_radius,
                          side=self.settings.context_side)
        mean, _, _ = self.learner.policy(x)
        return mean.clamp(-1.0, 1.0).cpu().numpy().astype(np.float32)
