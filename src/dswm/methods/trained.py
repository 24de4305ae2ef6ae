"""What the hand-written torch learners (MADDPG, GA-MATR, HRL-TPRA) share: the day schedule, the checkpointed
training loop, the training manifest, the model file and the checks at reset.

A method subclasses :class:`TrainedController` and gives it three hooks: ``make_trainer`` (its Trainer over the
training core), ``model_state`` (the learner's weights for the model file) and ``build_learner`` (a learner with
those weights). Its Trainer offers ``progress`` ((units done, units in all), the unit of ``checkpoint_every``),
``advance()`` (one unit), ``save(path, key)``/``restore(blob)`` (the whole run state), ``days_used`` (the core day of
every day-episode, in order), ``per_day``, ``history`` (its :class:`CurveLog`'s) and ``learner.steps``.
"""
from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path
from typing import Any, ClassVar, Mapping, Sequence

import numpy as np
import torch

from dswm.config import stable_hash, to_plain
from dswm.methods.base import Controller, DayContext, training_inputs_hash
from dswm.sim.core import Grid
from prep.atomic import atomic_path


def day_schedule(n_days: int, n_episodes: int, seed: int) -> np.ndarray:
    """(n_episodes,) core day of each day-episode: shuffled passes over the ``n_days`` days, drawn from ``seed``."""
    rng = np.random.default_rng(seed)
    passes = [rng.permutation(n_days) for _ in range(math.ceil(n_episodes / n_days))]
    return np.concatenate(passes)[:n_episodes].astype(np.int64)


def checkpoint_key(*, method: str, seed: int, settings: Any, core) -> dict:
    """What a checkpoint must match to be continued: method, seed, settings and training inputs."""
    return {"method": method, "seed": seed, "settings": stable_hash(to_plain(settings)),
            "inputs": training_inputs_hash(core)}


class CurveLog:
    """A training curve of at most ``log_points`` points per metric: the values added during a window of units
    (rounds or day-episodes) are averaged into one point, written at the end of every window and at the last unit
    with the transition count as its step (NaN for a metric without a value in the window)."""

    def __init__(self, names, *, units: int, log_points: int):
        self.units = units
        self.window = max(1, math.ceil(units / log_points))
        self.history: dict[str, list[float]] = {"step": [], **{n: [] for n in names}}
        self.acc: dict[str, list[float]] = {n: [] for n in names}

    def add(self, name: str, *values: float) -> None:
        self.acc[name].extend(float(v) for v in values)

    def end_unit(self, done: int, transitions: int) -> None:
        """Unit ``done`` is over (1-based); close the window when it ends there."""
        if done % self.window and done != self.units:
            return
        self.history["step"].append(transitions)
        for name, values in self.acc.items():
            self.history[name].append(float(np.mean(values)) if values else float("nan"))
        self.acc = {k: [] for k in self.acc}

    def state_dict(self) -> dict:
        return {"history": self.history, "acc": self.acc}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        self.history, self.acc = state["history"], state["acc"]


class UnitTrainer:
    """``history``, ``progress`` and ``advance`` of a Trainer that runs in units of ``unit`` ("round" or
    "episode"): its counter is the attribute ``<unit>``, its total ``n_<unit>s``, its step ``run_<unit>()``, its
    training curve the :class:`CurveLog` ``curve``."""

    unit: ClassVar[str]

    @property
    def history(self) -> dict[str, list[float]]:
        """The training curve (``CurveLog.history``)."""
        return self.curve.history

    @property
    def progress(self) -> tuple[int, int]:
        """(units done, units in all): the unit of ``checkpoint_every``."""
        return getattr(self, self.unit), getattr(self, f"n_{self.unit}s")

    def advance(self) -> None:
        """Run one unit."""
        getattr(self, f"run_{self.unit}")()


def training_manifest(trainer, core, checkpoint: Path) -> dict:
    """The training manifest of a finished run: every day-episode as a tensor day, counts, checkpoint, history."""
    day_ids = np.asarray(getattr(core, "day_ids", range(core.n_days)), dtype=np.int64)
    days = trainer.days_used
    return {"days": [int(day_ids[d]) for d in days], "day_labels": [core.day_labels[d] for d in days],
            "transitions_per_day_episode": trainer.per_day, "n_transitions": trainer.per_day * len(days),
            "steps": trainer.learner.steps, "checkpoint": str(checkpoint),
            "checkpoint_written_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(checkpoint.stat().st_mtime)),
            "read_test_data": False, "history": trainer.history}


class TrainedController(Controller):
    """A learning controller around a Trainer and its learner; acting is batched and deterministic."""

    learns: ClassVar[bool] = True
    batched: ClassVar[bool] = True
    model_label: ClassVar[str] = ""
    """The method's name in a model file's errors ("MADDPG")."""
    model_keys: ClassVar[tuple[str, ...]] = ()
    """The entries :meth:`model_state` writes."""

    def __init__(self, *, name: str, seed: int = 0, device: str = "cpu", options: Any = None):
        super().__init__(name=name, seed=seed, device=device, options=options)
        self.learner = None
        self.grid: Grid | None = None
        self.scenario = None

    @property
    def settings(self):
        """The method's typed settings (its ``options``)."""
        return self.options

    # ---- hooks -------------------------------------------------------------------------------------------
    def make_trainer(self, train_core):
        """The method's Trainer over the TRAINING-days core."""
        raise NotImplementedError

    def model_state(self) -> dict:
        """The learner's entries of the model file (``model_keys``)."""
        raise NotImplementedError

    def build_learner(self, grid: Grid, scenario, blob: Mapping[str, Any]):
        """A learner for ``grid`` and ``scenario`` with the weights of a model file's ``blob``."""
        raise NotImplementedError

    def use(self, learner, grid: Grid, scenario) -> None:
        """Act with ``learner`` from now on (trained on ``grid`` under ``scenario``)."""
        self.learner, self.grid, self.scenario = learner, grid, scenario

    # ---- training ----------------------------------------------------------------------------------------
    def fit(self, train_core, *, run_dir, snapshots=None) -> dict:
        """Train on the TRAINING-days core, continuing a checkpoint of the same run; return the manifest.
        ``snapshots``: see ``Controller.fit`` (one is taken after the unit that reaches each fraction)."""
        run_dir = Path(run_dir)
        run_dir.mkdir(parents=True, exist_ok=True)
        trainer = self.make_trainer(train_core)
        ckpt = run_dir / "checkpoint.pt"
        key = checkpoint_key(method=self.name, seed=self.seed, settings=self.settings, core=train_core)

        def write_snapshot(path: Path) -> None:
            self.use(trainer.learner, train_core.grid, train_core.scenario)
            self.save(path)

        if snapshots is not None:
            snapshots.claim(ckpt)
        if ckpt.exists():
            blob = torch.load(ckpt, map_location="cpu", weights_only=False)  # RNG states live on the CPU
            if blob.get("extra") == key:  # the same run, interrupted (or done): continue it
                trainer.restore(blob)
            del blob
        every = self.settings.checkpoint_every
        done, total = trainer.progress
        if snapshots is not None:
            snapshots.start(total=total, n_transitions=trainer.per_day * len(trainer.days_used),
                            gradient_steps=trainer.learner.steps, write=write_snapshot)
        while done < total:
            trainer.advance()
            done, total = trainer.progress
            if snapshots is not None:
                snapshots.step(done=done, total=total, n_transitions=trainer.per_day * len(trainer.days_used),
                               gradient_steps=trainer.learner.steps, write=write_snapshot)
            if done % every == 0 or done == total:
                trainer.save(ckpt, key)
        self.use(trainer.learner, train_core.grid, train_core.scenario)
        return training_manifest(trainer, train_core, ckpt)

    # ---- model file --------------------------------------------------------------------------------------
    def save(self, path) -> None:
        """The learner's weights, the architecture, grid and scenario they were trained on (one file, atomic)."""
        if self.learner is None:
            raise RuntimeError(f"{self.name}: nothing to save, the model is not trained")
        blob = {**self.model_state(), "architecture": self.settings.architecture(),
                "grid": dataclasses.asdict(self.grid), "scenario": self.scenario, "method": self.name,
                "seed": self.seed}
        with atomic_path(path) as tmp:
            torch.save(blob, tmp)

    def load(self, path) -> None:
        blob = torch.load(path, map_location=self.device, weights_only=False)
        missing = {*self.model_keys, "architecture", "grid", "scenario"} - set(blob if isinstance(blob, dict) else ())
        if missing:
            raise ValueError(f"{path}: not a {self.model_label} model file (missing the keys {sorted(missing)})")
        if blob["architecture"] != self.settings.architecture():
            raise ValueError(f"{path}: networks of architecture {blob['architecture']}; methods.{self.name} "
                             f"expects {self.settings.architecture()}; retrain it")
        grid, scenario = Grid(**blob["grid"]), blob["scenario"]
        self.use(self.build_learner(grid, scenario, blob), grid, scenario)

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

    def observation_tensors(self, obs: Mapping[str, Any]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(demand, fleet, time) of a batched observation as float32 tensors on the learner's device."""
        dev = self.learner.device
        return tuple(torch.as_tensor(np.asarray(obs[k]), dtype=torch.float32, device=dev)
                     for k in ("demand", "fleet", "time"))

    def reset(self, ctx: DayContext) -> None:
        self.reset_batch([ctx])

    def act(self, obs: Mapping[str, Any]) -> np.ndarray:
        return self.act_batch({k: np.asarray(v)[None] for k, v in obs.items()})[0]
