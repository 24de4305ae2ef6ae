"""The HRL-TPRA controller: ``fit`` on the training core, then deterministic batched acting."""
from __future__ import annotations

from typing import Any, ClassVar, Mapping, Sequence

import numpy as np
import torch

from dswm.methods.base import DayContext
from dswm.methods.hrl_tpra.features import Frame, compose_action, low_inputs, plan_inputs, slot_of
from dswm.methods.hrl_tpra.learner import Learner
from dswm.methods.hrl_tpra.settings import HRLTPRASettings
from dswm.methods.hrl_tpra.training import Trainer
from dswm.methods.trained import TrainedController
from dswm.sim.core import Grid


class HRLTPRAController(TrainedController):
    """HRL-TPRA (Yuan et al. 2025, re-implemented): a pointer-network planner assigns target cells per macro-slot,
    per-UAV resource actors move around the way there and set the bandwidth logits.

    ``act_batch`` acts without sampling on B days at once: at slots 0, m, 2m, ... (the slot is read from the time
    phase) the planner decodes greedily; at every slot the actors' Gaussian means are composed with the move toward
    each UAV's target and clipped to [-1, 1].
    """

    options_type: ClassVar[type] = HRLTPRASettings
    model_label: ClassVar[str] = "HRL-TPRA"
    model_keys: ClassVar[tuple[str, ...]] = ("planner", "plan_critic", "actors")

    def __init__(self, *, name: str, seed: int = 0, device: str = "cpu", options: HRLTPRASettings):
        super().__init__(name=name, seed=seed, device=device, options=options)
        self.frame: Frame | None = None
        self.targets: torch.Tensor | None = None

    def make_trainer(self, train_core) -> Trainer:
        return Trainer(core=train_core, settings=self.settings, seed=self.seed, device=self.device)

    def use(self, learner: Learner, grid: Grid, scenario) -> None:
        super().use(learner, grid, scenario)
        self.frame = Frame.of(grid, scenario, learner.device)
        self.targets = None

    def model_state(self) -> dict:
        """Planner, its critic, actors and their critics."""
        net = self.learner
        return {"planner": net.planner.state_dict(), "plan_critic": net.plan_critic.state_dict(),
                "actors": net.actors.state_dict()}

    def build_learner(self, grid: Grid, scenario, blob: Mapping[str, Any]) -> Learner:
        learner = Learner(settings=self.settings, n_uavs=scenario.n_uavs, device=self.device)
        learner.planner.load_state_dict(blob["planner"])
        learner.plan_critic.load_state_dict(blob["plan_critic"])
        learner.actors.load_state_dict(blob["actors"])
        return learner

    # ---- acting ------------------------------------------------------------------------------------------
    def reset_batch(self, ctxs: Sequence[DayContext]) -> None:
        """Check the days (grid, scenario) and forget the plans."""
        super().reset_batch(ctxs)
        self.targets = None

    def act_batch(self, obs: Mapping[str, Any]) -> np.ndarray:
        """(B, K, 3) float32 in [-1, 1]: greedy plans at macro-slot starts, the actors' means at every slot."""
        if self.learner is None:
            raise RuntimeError(f"{self.name}: act before fit() or load()")
        s, net, frame = self.settings, self.learner, self.frame
        demand, fleet, t = self.observation_tensors(obs)
        slot = slot_of(t, self.scenario.slots_per_day).to(net.device)
        with torch.no_grad():
            replan = slot % s.macro_slots == 0
            if self.targets is None or self.targets.shape[0] != len(slot):
                replan = torch.ones_like(replan)
            if bool(replan.any()):
                plan = plan_inputs(demand, fleet, t, frame, s.candidates)
                fresh = plan.cells.gather(1, net.planner(plan.cand, plan.uav, plan.dist, greedy=True).choice)
                self.targets = fresh if self.targets is None or self.targets.shape != fresh.shape else torch.where(
                    replan.unsqueeze(-1), fresh, self.targets)
            phase = (slot % s.macro_slots).to(torch.float32) / s.macro_slots
            local, _ = low_inputs(demand, fleet, t, self.targets, phase, frame, s.crop_radius)
            out = net.actors.mean(local).clamp(-1.0, 1.0)
            action = compose_action(out, fleet, self.targets, frame, s.fine_scale)
        return action.clamp(-1.0, 1.0).cpu().numpy().astype(np.float32)
