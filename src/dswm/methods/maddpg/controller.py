"""The MADDPG controller: ``fit`` on the training core, then deterministic batched acting."""
from __future__ import annotations

from typing import Any, ClassVar, Mapping

import numpy as np

from dswm.methods.maddpg.learner import Learner
from dswm.methods.maddpg.settings import MADDPGSettings
from dswm.methods.maddpg.training import Trainer
from dswm.methods.trained import TrainedController
from dswm.sim.core import Grid


class MADDPGController(TrainedController):
    """MADDPG (Lowe et al. 2017) for the UAV fleet: a shared actor on local observations, a centralized critic.

    ``act_batch`` runs the actor without noise on B days at once (the (B, K) agents through one shared network)
    and clips to [-1, 1].
    """

    options_type: ClassVar[type] = MADDPGSettings
    model_label: ClassVar[str] = "MADDPG"
    model_keys: ClassVar[tuple[str, ...]] = ("actor", "critic")

    def make_trainer(self, train_core) -> Trainer:
        """Training through the PettingZoo parallel API on the TRAINING-days core."""
        return Trainer(core=train_core, settings=self.settings, seed=self.seed, device=self.device)

    def model_state(self) -> dict:
        return {"actor": self.learner.actor.state_dict(), "critic": self.learner.critic.state_dict()}

    def build_learner(self, grid: Grid, scenario, blob: Mapping[str, Any]) -> Learner:
        learner = Learner(settings=self.settings, rows=grid.rows, cols=grid.cols, maps=scenario.obs_window + 1,
                          n_agents=scenario.n_uavs, device=self.device)
        learner.actor.load_state_dict(blob["actor"])
        learner.critic.load_state_dict(blob["critic"])
        return learner

    def act_batch(self, obs: Mapping[str, Any]) -> np.ndarray:
        """(B, K, 3) float32: the actor's deterministic actions (no noise), clipped to [-1, 1]."""
        return self.learner.act(*self.observation_tensors(obs)).clamp(-1.0, 1.0).cpu().numpy().astype(np.float32)
