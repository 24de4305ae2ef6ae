"""TD-MPC's controller: training on TRAINING days (a heuristic pre-collection plus its own interaction) and MPPI at
decision time.

``fit``:
1. the pre-collection (``dswm.methods.collect.collect`` with ``methods.tdmpc.precollect``, by choice DSWM's
   heuristic and size, the same seed), with the rewards of its transitions recomputed
   (``TransitionReplay.from_precollected``);
2. ``seed_steps`` gradient steps on it;
3. ``episodes`` own day-episodes on the training days (round-robin after the pre-collection's), ``parallel`` at a
   time, acting by MPPI with its final std as noise (or the policy plus noise), each round followed by an equal
   share of the remaining gradient steps;
4. complete checkpoints (weights, target, optimizers, replay, RNG states, step, history) written atomically every
   ``checkpoint_every`` steps and at every round's end; a run resumes from one (same settings and inputs) and ends
   where the uninterrupted run ends.
Per slot, for B days at once: encode, then MPPI (``dswm.methods.tdmpc.planner``) warm-started from each day's
previous mean; the executed move is clipped to [-1, 1] and (dx, dy) to the unit disk (a displacement of at most
D_max, as the environment would fly it).
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
from dswm.methods.collect import collect
from dswm.methods.tdmpc.learner import METRICS, Learner
from dswm.methods.tdmpc.model import TOLD
from dswm.methods.tdmpc.planner import mppi
from dswm.methods.tdmpc.replay import TransitionReplay
from dswm.methods.tdmpc.settings import TDMPCSettings, resolve
from dswm.sim.core import Grid
from prep.atomic import atomic_path

CHARTS = ("charts/episode_reward", "charts/served_ratio")
"""Per-slot reward and served ratio of the latest own-interaction round (before the first: of the pre-collection)."""


def project(action: torch.Tensor) -> torch.Tensor:
    """(..., K, 3) -> the same clipped to [-1, 1], with (dx, dy) scaled into the unit disk (|move| <= D_max)."""
    a = action.clamp(-1.0, 1.0)
    move = a[..., :2]
    scale = torch.clamp(1.0 / torch.linalg.vector_norm(move, dim=-1, keepdim=True).clamp_min(1e-12), max=1.0)
    return torch.cat([move * scale, a[..., 2:]], -1)


def round_bounds(settings: TDMPCSettings) -> list[int]:
    """Gradient-step count at the end of the seed phase and of every interaction round."""
    n_rounds = math.ceil(settings.episodes / settings.parallel)
    if n_rounds == 0:
        return [settings.steps]
    rest = settings.steps - settings.seed_steps
    return [settings.seed_steps + (rest * r) // n_rounds for r in range(n_rounds + 1)]


class TDMPCController(Controller):
    """TD-MPC (Hansen et al. 2022) for the fleet; see the module docstring. Settings: ``TDMPCSettings``."""

    learns = True
    batched = True
    options_type: ClassVar[type] = TDMPCSettings

    def __init__(self, *, name: str, seed: int = 0, device: str = "cpu", options: TDMPCSettings):
        super().__init__(name=name, seed=seed, device=device, options=options)
        self.model: TOLD | None = None
        self.plan_ms: list[float] = []

    @property
    def settings(self) -> TDMPCSettings:
        return self.options

    @classmethod
    def options_from_config(cls, *, name: str, config: Mapping[str, Any], profile: str) -> TDMPCSettings:
        """``methods.<name>`` with its profile budget (``dswm.methods.tdmpc.settings``)."""
        return resolve(config, name=name, profile=profile)

    def settings_hash(self) -> str:
        return stable_hash(to_plain(self.settings))

    def _build_model(self, grid: Grid, scenario) -> TOLD:
        self.grid, self.scenario = grid, scenario
        s = self.settings
        return TOLD(window=scenario.obs_window + 1, rows=grid.rows, cols=grid.cols, n_uavs=scenario.n_uavs,
                    latent=s.latent, hidden=s.hidden, channels=s.enc_channels).to(self.device)

    # ---- planning ------------------------------------------------------------------------------------------
    def _tensors(self, obs: Mapping[str, Any]) -> tuple[torch.Tensor, ...]:
        return tuple(torch.as_tensor(np.asarray(obs[k]), dtype=torch.float32, device=self.device)
                     for k in ("demand", "fleet", "time"))

    @torch.no_grad()
    def _decide(self, obs: Mapping[str, Any], *, generator: torch.Generator, explore: bool = False) -> torch.Tensor:
        """(B, K, 3) projected actions for a batched observation; keeps each day's MPPI mean for the next slot."""
        z = self.model.encode(*self._tensors(obs))
        b, k = z.shape[0], self.scenario.n_uavs
        if explore and self.settings.explore == "policy":
            a = self.model.pi(z, self.settings.explore_std, generator)
        else:
            res = mppi(self.model, z, cfg=self.settings.mppi(), generator=generator, prev_mean=self.prev_mean,
                       explore=explore)
            self.prev_mean, a = res.mean, res.action
        return project(a.reshape(b, k, 3))

    # ---- training ------------------------------------------------------------------------------------------
    def _play(self, core, rows: list[int], replay: TransitionReplay, generator: torch.Generator) -> dict[str, float]:
        """One own day-episode per training-core day in ``rows``, stored in ``replay``; mean reward and SR."""
        obs = core.reset(rows)
        self.prev_mean = None
        fleet, acts, srs, rews, terms = [obs["fleet"]], [], [], [], []
        for _ in range(core.scenario.slots_per_day - 1):
            a = self._decide(obs, generator=generator, explore=True).cpu().numpy()
            out = core.step(a)
            obs = out.obs
            fleet.append(obs["fleet"])
            acts.append(a)
            srs.append(out.sr)
            rews.append(out.reward)
            terms.append(out.terminated)
        fleet, acts, srs, rews, terms = (np.stack(x, 1) for x in (fleet, acts, srs, rews, terms))
        for j, r in enumerate(rows):
            replay.add_episode(row=r, fleet=fleet[j], actions=acts[j], next_sr=srs[j], reward=rews[j],
                               terminated=terms[j], own=True)
        return {"charts/episode_reward": float(rews.mean()), "charts/served_ratio": float(srs.mean())}

    def fit(self, train_core, *, run_dir, snapshots=None) -> dict:
        """Train on the TRAINING-days core (module docstring), checkpoint under ``run_dir``; return the manifest.
        ``snapshots``: see ``Controller.fit`` (the budget is the gradient steps; the transitions are those in the
        replay at that step, the pre-collected ones included)."""
        s, run_dir = self.settings, Path(run_dir)
        run_dir.mkdir(parents=True, exist_ok=True)
        day_ids = np.asarray(getattr(train_core, "day_ids", range(train_core.n_days)), dtype=np.int64)
        torch.manual_seed(self.seed)
        pre = collect(train_core, n_transitions=s.precollect.transitions, cfg=s.precollect,
                      seed=self.seed, day_ids=day_ids)
        replay = TransitionReplay.from_precollected(pre, grid=train_core.grid, scenario=train_core.scenario)
        self.model = self._build_model(train_core.grid, train_core.scenario)
        learner = Learner(self.model, s, seed=self.seed)
        explore_gen = torch.Generator(device=self.device).manual_seed(self.seed)
        bounds = round_bounds(s)
        n_pre = len(replay)
        charts = {"charts/episode_reward": replay.mean_reward(), "charts/served_ratio":
                  float(torch.cat(replay.next_sr).mean())}
        run = {"rounds_done": 0, "history": {"step": [], **{f"losses/{m}": [] for m in METRICS},
                                             **{c: [] for c in CHARTS}},
               "acc": dict.fromkeys(METRICS, 0.0), "n_acc": 0, "charts": charts}
        ckpt = run_dir / "checkpoint.pt"
        extra = {"method": self.name, "seed": self.seed, "settings": self.settings_hash(),
                 "inputs": training_inputs_hash(train_core, day_ids)}
        if snapshots is not None:
            snapshots.claim(ckpt)
        if ckpt.exists():
            blob = torch.load(ckpt, map_location=self.device, weights_only=False)
            if blob.get("extra") == extra:      # the same run (settings, seed, data): continue it
                learner.load_state_dict(blob["learner"])
                replay = TransitionReplay.from_state_dict(blob["replay"], grid=train_core.grid,
                                                          scenario=train_core.scenario)
                explore_gen.set_state(blob["explore_rng"])
                torch.set_rng_state(blob["torch_rng"])
                run = blob["run"]

        def checkpoint() -> None:
            blob = {"learner": learner.state_dict(), "replay": replay.state_dict(), "run": run,
                    "explore_rng": explore_gen.get_state(), "torch_rng": torch.get_rng_state(), "extra": extra}
            with atomic_path(ckpt) as tmp:
                torch.save(blob, tmp)

        window = max(1, s.steps // s.log_points)
        if snapshots is not None:
            snapshots.start(total=s.steps, n_transitions=replay.n_transitions, gradient_steps=learner.step,
                            write=self.save)

        def train_until(target: int) -> None:
            while learner.step < target:
                metrics = learner.train_step(replay)
                for m in METRICS:
                    run["acc"][m] += metrics[m]
                run["n_acc"] += 1
                if run["n_acc"] == window or learner.step == s.steps:
                    run["history"]["step"].append(learner.step)
                    for m in METRICS:
                        run["history"][f"losses/{m}"].append(run["acc"][m] / run["n_acc"])
                    for c in CHARTS:
                        run["history"][c].append(run["charts"][c])
                    run["acc"], run["n_acc"] = dict.fromkeys(METRICS, 0.0), 0
                if snapshots is not None:
                    snapshots.step(done=learner.step, total=s.steps, n_transitions=replay.n_transitions,
                                   gradient_steps=learner.step, write=self.save)
                if learner.step % s.checkpoint_every == 0 or learner.step == target:
                    checkpoint()

        train_until(bounds[run["rounds_done"]])      # the seed phase, or the rest of the round a resume stopped in
        for r in range(run["rounds_done"], len(bounds) - 1):
            first = r * s.parallel
            rows = [(n_pre + first + j) % train_core.n_days for j in range(min(s.parallel, s.episodes - first))]
            run["charts"] = self._play(train_core, rows, replay, explore_gen)
            run["rounds_done"] = r + 1
            if learner.step == bounds[r + 1]:
                checkpoint()
            train_until(bounds[r + 1])
        if not ckpt.exists():
            checkpoint()
        self.replay = replay
        return {"days": replay.episode_days(), "day_labels": [train_core.day_labels[r] for r in replay.rows],
                "transitions_per_day_episode": train_core.scenario.slots_per_day - 1,
                "n_transitions": replay.n_transitions, "steps": s.steps, "checkpoint": str(ckpt),
                "checkpoint_written_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(ckpt.stat().st_mtime)),
                "read_test_data": False, "history": run["history"]}

    # ---- model file ----------------------------------------------------------------------------------------
    def save(self, path) -> None:
        """Weights, grid, scenario and the settings they were built with, in one file written atomically."""
        if self.model is None:
            raise RuntimeError(f"{self.name}: nothing to save, the model is not trained")
        blob = {"model": self.model.state_dict(), "grid": dataclasses.asdict(self.grid), "scenario": self.scenario,
                "settings": to_plain(self.settings), "method": self.name, "seed": self.seed}
        with atomic_path(path) as tmp:
            torch.save(blob, tmp)

    def load(self, path) -> None:
        blob = torch.load(path, map_location=self.device, weights_only=False)
        if not isinstance(blob, dict) or any(k not in blob for k in ("model", "grid", "scenario", "settings")):
            raise ValueError(f"{path}: not a TD-MPC model file (expected the keys model, grid, scenario, settings)")
        sizes = ("latent", "hidden", "enc_channels")
        if any(blob["settings"][k] != getattr(self.settings, k) for k in sizes):
            raise ValueError(f"{path}: built with {({k: blob['settings'][k] for k in sizes})}, the settings say "
                             f"{({k: getattr(self.settings, k) for k in sizes})}; retrain it")
        self.model = self._build_model(Grid(**blob["grid"]), blob["scenario"])
        self.model.load_state_dict(blob["model"])
        self.model.eval()

    # ---- acting --------------------------------------------------------------------------------------------
    def reset_batch(self, ctxs: Sequence[DayContext]) -> None:
        if self.model is None:
            raise RuntimeError(f"{self.name}: reset_batch() before fit() or load()")
        for ctx in ctxs:
            g = ctx.grid
            if (g.rows, g.cols) != (self.model.rows, self.model.cols):
                raise ValueError(f"{self.name}: model trained on a {self.model.rows}x{self.model.cols} grid, day "
                                 f"{ctx.label} of {ctx.dataset} has {g.rows}x{g.cols}")
            if ctx.scenario.hash() != self.scenario.hash():
                raise ValueError(f"{self.name}: model trained under scenario hash {self.scenario.hash()}, day "
                                 f"{ctx.label} of {ctx.dataset} is evaluated under {ctx.scenario.hash()}; retrain it")
        self.prev_mean = None
        seed = int(stable_hash({"seed": self.seed, "days": [int(c.day) for c in ctxs]}), 16) % (2**63)
        self.generator = torch.Generator(device=self.device).manual_seed(seed)

    def act_batch(self, obs: Mapping[str, Any]) -> np.ndarray:
        t0 = time.perf_counter()
        with torch.inference_mode():
            action = self._decide(obs, generator=self.generator)
        self.plan_ms.append(1000.0 * (time.perf_counter() - t0))
        return action.cpu().numpy().astype(np.float32)

    def reset(self, ctx: DayContext) -> None:
        self.reset_batch([ctx])

    def act(self, obs: Mapping[str, Any]) -> np.ndarray:
        return self.act_batch({k: np.asarray(v)[None] for k, v in obs.items()})[0]
