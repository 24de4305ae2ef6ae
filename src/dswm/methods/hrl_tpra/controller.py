"""The HRL-TPRA controller: ``fit`` on the training core, then deterministic batched acting."""
from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any, ClassVar, Mapping, Sequence

import numpy as np
import torch

from dswm.methods.base import Controller, DayContext
from dswm.methods.hrl_tpra.features import Frame, compose_action, low_inputs, plan_inputs, slot_of
from dswm.methods.hrl_tpra.learner import Learner
from dswm.methods.hrl_tpra.settings import HRLTPRASettings
from dswm.methods.hrl_tpra.training import Trainer, checkpoint_key
from dswm.sim.core import Grid
from prep.atomic import atomic_path


class HRLTPRAController(Controller):
    """HRL-TPRA (Yuan et al. 2025, re-implemented): a pointer-network planner assigns target cells per macro-slot,
    per-UAV resource actors move around the way there and set the bandwidth logits.

    ``act_batch`` acts without sampling on B days at once: at slots 0, m, 2m, ... (the slot is read from the time
    phase) the planner decodes greedily; at every slot the actors' Gaussian means are composed with the move toward
    each UAV's target and clipped to [-1, 1].
    """

    learns: ClassVar[bool] = True
    batched: ClassVar[bool] = True
    options_type: ClassVar[type] = HRLTPRASettings

    def __init__(self, *, name: str, seed: int = 0, device: str = "cpu", options: HRLTPRASettings):
        super().__init__(name=name, seed=seed, device=device, options=options)
        self.learner: Learner | None = None
        self.grid: Grid | None = None
        self.scenario = None
        self.frame: Frame | None = None
        self.targets: torch.Tensor | None = None

    @property
    def settings(self) -> HRLTPRASettings:
        """The method's typed settings (its ``options``)."""
        return self.options

    # ---- training ----------------------------------------------------------------------------------------
    def fit(self, train_core, *, run_dir) -> dict:
        """Train on the TRAINING-days core; checkpoint; return the manifest (every day-episode used, in order)."""
        run_dir = Path(run_dir)
        run_dir.mkdir(parents=True, exist_ok=True)
        trainer = Trainer(core=train_core, settings=self.settings, seed=self.seed, device=self.device)
        ckpt = run_dir / "checkpoint.pt"
        key = checkpoint_key(method=self.name, seed=self.seed, settings=self.settings, core=train_core)
        if ckpt.exists():
            blob = torch.load(ckpt, map_location="cpu", weights_only=False)  # RNG states live on the CPU
            if blob.get("extra") == key:  # the same run, interrupted (or done): continue it
                trainer.restore(blob)
            del blob
        every = self.settings.checkpoint_every
        while trainer.round < trainer.n_rounds:
            trainer.run_round()
            if trainer.round % every == 0 or trainer.round == trainer.n_rounds:
                trainer.save(ckpt, key)
        self._use(trainer.learner, train_core.grid, train_core.scenario)
        day_ids = np.asarray(getattr(train_core, "day_ids", range(train_core.n_days)), dtype=np.int64)
        days = trainer.days_used
        return {"days": [int(day_ids[d]) for d in days], "day_labels": [train_core.day_labels[d] for d in days],
                "transitions_per_day_episode": trainer.per_day, "n_transitions": trainer.per_day * len(days),
                "steps": trainer.learner.steps, "checkpoint": str(ckpt),
                "checkpoint_written_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(ckpt.stat().st_mtime)),
                "read_test_data": False, "history": trainer.history}

    def _use(self, learner: Learner, grid: Grid, scenario) -> None:
        self.learner, self.grid, self.scenario = learner, grid, scenario
        self.frame = Frame.of(grid, scenario, learner.device)
        self.targets = None

    # ---- model file --------------------------------------------------------------------------------------
    def save(self, path) -> None:
        """Planner, actors and critics, the architecture, grid and scenario they were trained on (one file, atomic)."""
        if self.learner is None:
            raise RuntimeError(f"{self.name}: nothing to save, the model is not trained")
        net = self.learner
        blob = {"planner": net.planner.state_dict(), "plan_critic": net.plan_critic.state_dict(),
                "actors": net.actors.state_dict(), "architecture": self.settings.architecture(),
                "grid": dataclasses.asdict(self.grid), "scenario": self.scenario, "method": self.name,
                "seed": self.seed}
        with atomic_path(path) as tmp:
            torch.save(blob, tmp)

    def load(self, path) -> None:
        blob = torch.load(path, map_location=self.device, weights_only=False)
        missing = {"planner", "plan_critic", "actors", "architecture", "grid", "scenario"} - set(
            blob if isinstance(blob, dict) else ())
        if missing:
            raise ValueError(f"{path}: not an HRL-TPRA model file (missing the keys {sorted(missing)})")
        if blob["architecture"] != self.settings.architecture():
            raise ValueError(f"{path}: networks of architecture {blob['architecture']}; methods.{self.name} "
                             f"expects {self.settings.architecture()}; retrain it")
        grid, scenario = Grid(**blob["grid"]), blob["scenario"]
        learner = Learner(settings=self.settings, n_uavs=scenario.n_uavs, device=self.device)
        learner.planner.load_state_dict(blob["planner"])
        learner.plan_critic.load_state_dict(blob["plan_critic"])
        learner.actors.load_state_dict(blob["actors"])
        self._use(learner, grid, scenario)

    # ---- acting ------------------------------------------------------------------------------------------
    def reset_batch(self, ctxs: Sequence[DayContext]) -> None:
        """Check that every day is on the grid and under the scenario the model was trained on; forget the plans."""
        if self.learner is None:
            raise RuntimeError(f"{self.name}: reset before fit() or load()")
        for ctx in ctxs:
            g = ctx.grid
            if (g.rows, g.cols) != (self.grid.rows, self.grid.cols):
                raise ValueError(f"{self.name}: model trained on a {self.grid.rows}x{self.grid.cols} grid, day "
                                 f"{ctx.label} of {ctx.dataset} has {g.rows}x{g.cols}")
            if ctx.scenario.hash() != self.scenario.hash():
                raise ValueError(f"{self.name}: model trained under scenario hash {self.scenario.hash()}, day "
                                 f"{ctx.label} of {ctx.dataset} is evaluated under {ctx.scenario.hash()}; retrain it")
        self.targets = None

    def act_batch(self, obs: Mapping[str, Any]) -> np.ndarray:
        """(B, K, 3) float32 in [-1, 1]: greedy plans at macro-slot starts, the actors' means at every slot."""
        if self.learner is None:
            raise RuntimeError(f"{self.name}: act before fit() or load()")
        s, net, frame = self.settings, self.learner, self.frame
        demand, fleet, t = (torch.as_tensor(np.asarray(obs[k]), dtype=torch.float32, device=net.device)
                            for k in ("demand", "fleet", "time"))
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

    def reset(self, ctx: DayContext) -> None:
        self.reset_batch([ctx])

    def act(self, obs: Mapping[str, Any]) -> np.ndarray:
        return self.act_batch({k: np.asarray(v)[None] for k, v in obs.items()})[0]
