"""The GA-MATR controller: ``fit`` on the training core, then deterministic batched acting."""
from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any, ClassVar, Mapping, Sequence

import numpy as np
import torch

from dswm.methods.base import Controller, DayContext
from dswm.methods.ga_matr.happo import Learner
from dswm.methods.ga_matr.networks import context_dim, policy_inputs, uav_dim
from dswm.methods.ga_matr.settings import GAMATRSettings
from dswm.methods.ga_matr.training import Trainer, checkpoint_key
from dswm.methods.rl.spaces import observation_dim
from dswm.sim.core import Grid
from prep.atomic import atomic_path


class GAMATRController(Controller):
    """GA-MATR (Feng et al. 2024, re-implemented): a graph-attention policy shared by the UAVs, trained by HAPPO's
    sequential per-agent updates with a centralized critic and a load-fairness term in the learner's reward.

    ``act_batch`` runs the policy's mean (no sampling) on B days at once, the (B, K) UAVs in one pass, clipped to
    [-1, 1].
    """

    learns: ClassVar[bool] = True
    batched: ClassVar[bool] = True
    options_type: ClassVar[type] = GAMATRSettings

    def __init__(self, *, name: str, seed: int = 0, device: str = "cpu", options: GAMATRSettings):
        super().__init__(name=name, seed=seed, device=device, options=options)
        self.learner: Learner | None = None
        self.grid: Grid | None = None
        self.scenario = None

    @property
    def settings(self) -> GAMATRSettings:
        """The method's typed settings (its ``options``)."""
        return self.options

    # ---- training ----------------------------------------------------------------------------------------
    def fit(self, train_core, *, run_dir) -> dict:
        """Train on the TRAINING-days core; checkpoint; return the manifest (every day-episode played, in order)."""
        run_dir = Path(run_dir)
        run_dir.mkdir(parents=True, exist_ok=True)
        trainer = Trainer(core=train_core, settings=self.settings, seed=self.seed, device=self.device)
        ckpt = run_dir / "checkpoint.pt"
        key = checkpoint_key(method=self.name, seed=self.seed, settings=self.settings, core=train_core)
        if ckpt.exists():
            blob = torch.load(ckpt, map_location="cpu", weights_only=False)  # the generator's state lives on the CPU
            if blob.get("extra") == key:  # the same run, interrupted (or done): continue it
                trainer.restore(blob)
            del blob
        every = self.settings.checkpoint_every
        while trainer.round < trainer.n_rounds:
            trainer.run_round()
            if trainer.round % every == 0 or trainer.round == trainer.n_rounds:
                trainer.save(ckpt, key)
        self.learner, self.grid, self.scenario = trainer.learner, train_core.grid, train_core.scenario
        day_ids = np.asarray(getattr(train_core, "day_ids", range(train_core.n_days)), dtype=np.int64)
        days = trainer.days_used
        return {"days": [int(day_ids[d]) for d in days], "day_labels": [train_core.day_labels[d] for d in days],
                "transitions_per_day_episode": trainer.per_day, "n_transitions": trainer.per_day * len(days),
                "steps": trainer.learner.steps, "checkpoint": str(ckpt),
                "checkpoint_written_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(ckpt.stat().st_mtime)),
                "read_test_data": False, "history": trainer.history}

    # ---- model file --------------------------------------------------------------------------------------
    def save(self, path) -> None:
        """Policy and critic weights, value normalizer, architecture, grid and scenario (one file, atomic)."""
        if self.learner is None:
            raise RuntimeError(f"{self.name}: nothing to save, the model is not trained")
        blob = {"policy": self.learner.policy.state_dict(), "critic": self.learner.critic.state_dict(),
                "value_norm": self.learner.value_norm.state_dict(), "architecture": self.settings.architecture(),
                "grid": dataclasses.asdict(self.grid), "scenario": self.scenario, "method": self.name,
                "seed": self.seed}
        with atomic_path(path) as tmp:
            torch.save(blob, tmp)

    def load(self, path) -> None:
        blob = torch.load(path, map_location=self.device, weights_only=False)
        missing = {"policy", "critic", "value_norm", "architecture", "grid", "scenario"} - set(
            blob if isinstance(blob, dict) else ())
        if missing:
            raise ValueError(f"{path}: not a GA-MATR model file (missing the keys {sorted(missing)})")
        if blob["architecture"] != self.settings.architecture():
            raise ValueError(f"{path}: networks of architecture {blob['architecture']}; methods.{self.name} "
                             f"expects {self.settings.architecture()}; retrain it")
        self.grid, self.scenario = Grid(**blob["grid"]), blob["scenario"]
        maps = self.scenario.obs_window + 1
        self.learner = Learner(settings=self.settings, n_agents=self.scenario.n_uavs,
                               uav_in=uav_dim(maps, self.settings.crop_radius), context_in=context_dim(maps),
                               obs_dim=observation_dim(self.grid.rows, self.grid.cols, self.scenario),
                               device=self.device)
        self.learner.policy.load_state_dict(blob["policy"])
        self.learner.critic.load_state_dict(blob["critic"])
        self.learner.value_norm.load_state_dict(blob["value_norm"])

    # ---- acting ------------------------------------------------------------------------------------------
    def reset_batch(self, ctxs: Sequence[DayContext]) -> None:
        """Check that every day is on the grid and under the scenario the model was trained on."""
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

    @torch.no_grad()
    def act_batch(self, obs: Mapping[str, Any]) -> np.ndarray:
        """(B, K, 3) float32: the policy's mean actions, clipped to [-1, 1]."""
        dev = self.learner.device
        demand, fleet, t = (torch.as_tensor(np.asarray(obs[k]), dtype=torch.float32, device=dev)
                            for k in ("demand", "fleet", "time"))
        x = policy_inputs(demand, fleet, t, radius=self.settings.crop_radius, side=self.settings.context_side)
        mean, _, _ = self.learner.policy(x)
        return mean.clamp(-1.0, 1.0).cpu().numpy().astype(np.float32)

    def reset(self, ctx: DayContext) -> None:
        self.reset_batch([ctx])

    def act(self, obs: Mapping[str, Any]) -> np.ndarray:
        return self.act_batch({k: np.asarray(v)[None] for k, v in obs.items()})[0]
