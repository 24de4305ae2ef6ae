"""The MADDPG controller: ``fit`` on the training core, then deterministic batched acting."""
from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any, ClassVar, Mapping, Sequence

import numpy as np
import torch

from dswm.methods.base import Controller, DayContext
from dswm.methods.maddpg.learner import Learner
from dswm.methods.maddpg.settings import MADDPGSettings
from dswm.methods.maddpg.training import Trainer, checkpoint_key
from dswm.sim.core import Grid
from prep.atomic import atomic_path


class MADDPGController(Controller):
    """MADDPG (Lowe et al. 2017) for the UAV fleet: a shared actor on local observations, a centralized critic.

    ``act_batch`` runs the actor without noise on B days at once (the (B, K) agents through one shared network)
    and clips to [-1, 1].
    """

    learns: ClassVar[bool] = True
    batched: ClassVar[bool] = True
    options_type: ClassVar[type] = MADDPGSettings

    def __init__(self, *, name: str, seed: int = 0, device: str = "cpu", options: MADDPGSettings):
        super().__init__(name=name, seed=seed, device=device, options=options)
        self.learner: Learner | None = None
        self.grid: Grid | None = None
        self.scenario = None

    @property
    def settings(self) -> MADDPGSettings:
        """The method's typed settings (its ``options``)."""
        return self.options

    # ---- training ----------------------------------------------------------------------------------------
    def fit(self, train_core, *, run_dir) -> dict:
        """Train on the TRAINING-days core through the PettingZoo parallel API; checkpoint; return the manifest."""
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
        while trainer.episode < trainer.n_episodes:
            trainer.run_episode()
            if trainer.episode % every == 0 or trainer.episode == trainer.n_episodes:
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
        """Actor and critic weights, the architecture, grid and scenario they were trained on (one file, atomic)."""
        if self.learner is None:
            raise RuntimeError(f"{self.name}: nothing to save, the model is not trained")
        blob = {"actor": self.learner.actor.state_dict(), "critic": self.learner.critic.state_dict(),
                "architecture": self.settings.architecture(), "grid": dataclasses.asdict(self.grid),
                "scenario": self.scenario, "method": self.name, "seed": self.seed}
        with atomic_path(path) as tmp:
            torch.save(blob, tmp)

    def load(self, path) -> None:
        blob = torch.load(path, map_location=self.device, weights_only=False)
        missing = {"actor", "critic", "architecture", "grid", "scenario"} - set(blob if isinstance(blob, dict) else ())
        if missing:
            raise ValueError(f"{path}: not a MADDPG model file (missing the keys {sorted(missing)})")
        if blob["architecture"] != self.settings.architecture():
            raise ValueError(f"{path}: networks of architecture {blob['architecture']}; methods.{self.name} "
                             f"expects {self.settings.architecture()}; retrain it")
        self.grid, self.scenario = Grid(**blob["grid"]), blob["scenario"]
        self.learner = self._learner(self.grid, self.scenario)
        self.learner.actor.load_state_dict(blob["actor"])
        self.learner.critic.load_state_dict(blob["critic"])

    def _learner(self, grid: Grid, scenario) -> Learner:
        return Learner(settings=self.settings, rows=grid.rows, cols=grid.cols, maps=scenario.obs_window + 1,
                       n_agents=scenario.n_uavs, device=self.device)

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

    def act_batch(self, obs: Mapping[str, Any]) -> np.ndarray:
        """(B, K, 3) float32: the actor's deterministic actions (no noise), clipped to [-1, 1]."""
        dev = self.learner.device
        demand, fleet, t = (torch.as_tensor(np.asarray(obs[k]), dtype=torch.float32, device=dev)
                            for k in ("demand", "fleet", "time"))
        return self.learner.act(demand, fleet, t).clamp(-1.0, 1.0).cpu().numpy().astype(np.float32)

    def reset(self, ctx: DayContext) -> None:
        self.reset_batch([ctx])

    def act(self, obs: Mapping[str, Any]) -> np.ndarray:
        return self.act_batch({k: np.asarray(v)[None] for k, v in obs.items()})[0]
