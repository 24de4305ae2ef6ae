"""Model-free RL with Stable-Baselines3: ``ppo`` and ``sac`` (the paper's "model-free RL" class).

Both learn an MLP policy on the one flat observation (:mod:`dswm.methods.rl.spaces`) over the TRAINING-days core
through :class:`dswm.methods.rl.vec_env.FleetVecEnv`; the algorithms, their losses and their updates are SB3's,
the project supplies the environment, the settings (config.yaml ``methods.ppo`` / ``methods.sac``) and the files.

* Budget: ``day_episodes`` whole day-episodes of 143 transitions, in rounds of ``n_envs`` days stepped together
  (``day_episodes`` is a multiple of ``n_envs``); each round is one ``learn`` call. PPO's rollout is exactly one
  round (``n_steps`` = 143): every rollout ends at the day's truncation, where SB3 adds gamma * V(terminal
  observation) to the last reward. SAC's replay buffer keeps ``handle_timeout_termination`` (its default), so a
  day's end is stored as a timeout and its TD target bootstraps.
* Checkpoint ``run_dir/checkpoint.zip``: SB3's own ``save`` of the algorithm (weights, optimizers, entropy
  coefficient, counters, last observation) plus the members ``dswm/meta.json`` (what the model acts on),
  ``dswm/state.pt`` (python, numpy and torch RNG states, the action space's RNG, the day draws and the record of
  days, the history, the rounds done and the run's identity) and, for SAC, ``dswm/replay_buffer.pkl``. It is
  written atomically every ``checkpoint_every`` rounds and at the end. A rerun of ``fit`` in the same run_dir
  resumes from it when the identity matches: same class, seed, settings other than ``day_episodes`` and
  ``checkpoint_every``, SB3 version and training inputs (:func:`training_inputs_hash`), and no more rounds done
  than asked; a resumed run reproduces the uninterrupted one exactly (the same next losses, the same days).
* Model file (``save``/``load``): SB3's zip with ``dswm/meta.json``, no replay buffer: what acting needs.
* Seeds: SB3's ``seed=`` (weights, sampling, minibatches), the env's day draws (``FleetVecEnv.seed``).
"""
from __future__ import annotations

import dataclasses
import io
import json
import math
import pickle
import random
import time
import zipfile
from pathlib import Path
from typing import Any, ClassVar, Mapping, Sequence

import numpy as np
import stable_baselines3
import torch
from stable_baselines3 import PPO
from stable_baselines3.common.base_class import BaseAlgorithm

from dswm.config import ENUM, setting, stable_hash, to_plain
from dswm.methods.base import Controller, DayContext, training_inputs_hash
from dswm.methods.matmul import MatmulDtype
from dswm.methods.rl.common import DumpEachUpdate, PPOParams, SB3Params, rng_states, set_rng_states
from dswm.methods.rl.logger import HistoryWriter, history_logger
from dswm.methods.rl.sac_train import SAC, ReplayBuffer
from dswm.methods.rl.spaces import DEMAND_TRANSFORM, fleet_action, flat_observation, observation_dim
from dswm.methods.rl.vec_env import FleetVecEnv
from prep.atomic import atomic_path

CHECKPOINT = "checkpoint.zip"
META_MEMBER = "dswm/meta.json"
STATE_MEMBER = "dswm/state.pt"
BUFFER_MEMBER = "dswm/replay_buffer.pkl"
MAX_HISTORY_POINTS = 200
"""At most this many points in a training history (a point averages several rounds when there are more)."""
RESUME_FREE = ("day_episodes", "checkpoint_every")
"""Settings a checkpoint may differ in and still resume (a longer budget continues a shorter run)."""


# ---- settings --------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True, kw_only=True)
class SB3Settings(SB3Params):
    """Settings shared by the SB3 methods (config.yaml ``methods.ppo`` / ``methods.sac``): the learner's
    (:class:`~dswm.methods.rl.common.SB3Params`) and the budget."""

    day_episodes: int = setting("count")
    """Training budget in whole day-episodes of 143 transitions, a multiple of n_envs."""
    checkpoint_every: int = setting("count")
    """Rounds between checkpoints (one is also written at the end)."""

    def __post_init__(self):
        super().__post_init__()
        if self.day_episodes % self.n_envs:
            self._fail("day_episodes", f"a multiple of n_envs = {self.n_envs} (training budgets are whole rounds)")


@dataclasses.dataclass(frozen=True, kw_only=True)
class PPOSettings(SB3Settings, PPOParams):
    """PPO (``methods.ppo``): :class:`~dswm.methods.rl.common.PPOParams`, its exploration and the budget."""

    section: ClassVar[str] = "methods.ppo"

    use_sde: bool = setting("flag")
    """SB3's generalized state-dependent exploration (gSDE, Raffin et al. 2022) in place of independent Gaussian noise
    per slot: the noise is a linear map of the policy's last hidden features whose matrix is drawn anew every
    ``sde_sample_freq`` slots, and ``log_std_init`` is the log std of that matrix's entries."""
    sde_sample_freq: int = setting(schema={"anyOf": [{"type": "integer", "minimum": 1}, {"const": -1}],
                                           "description": "an integer >= 1, or -1 (once per rollout)"})
    """With ``use_sde``: slots between draws of the noise matrix (-1: one draw per rollout, i.e. per day)."""

    def ppo_kwargs(self, horizon: int) -> dict:
        """:meth:`PPOParams.ppo_kwargs` with the exploration: gSDE's two keys where ``use_sde`` is on."""
        kwargs = super().ppo_kwargs(horizon)
        if self.use_sde:
            kwargs.update(use_sde=True, sde_sample_freq=self.sde_sample_freq)
        return kwargs


@dataclasses.dataclass(frozen=True, kw_only=True)
class SACSettings(SB3Settings):
    """SAC (``methods.sac``)."""

    section: ClassVar[str] = "methods.sac"

    buffer_size: int = setting("count")
    """Replay capacity in transitions (each holds two flat observations: memory ~ 8 D bytes per transition)."""
    learning_starts: int = setting("natural")
    """Transitions of uniform random actions before the first update."""
    tau: float = setting("discount")
    """Polyak rate of the target critics."""
    train_freq: int = setting("count")
    """Vectorized steps (n_envs transitions each) between updates."""
    gradient_steps: int = setting("count")
    """Gradient steps per update."""
    ent_coef_init: float = setting("positive")
    """Initial entropy coefficient."""
    auto_entropy: bool = setting("flag")
    """Learn the entropy coefficient towards SB3's target entropy -dim(action) (else keep ent_coef_init)."""
    matmul_dtype: MatmulDtype = setting(ENUM)
    """The dtype of the networks' matrix products, float32 everything else (:mod:`dswm.methods.matmul`)."""

    def __post_init__(self):
        super().__post_init__()
        if self.buffer_size < self.batch_size:
            self._fail("buffer_size", f"at least batch_size = {self.batch_size}")


# ---- controllers -----------------------------------------------------------------------------------------
class SB3Controller(Controller):
    """An SB3 algorithm on the flat observation; subclasses name the algorithm and its keyword arguments."""

    learns = True
    batched = True
    algorithm: ClassVar[type[BaseAlgorithm]]

    def __init__(self, *, name: str, seed: int = 0, device: str = "cpu", options: Any = None):
        super().__init__(name=name, seed=seed, device=device, options=options)
        self.model: BaseAlgorithm | None = None
        self.meta: dict | None = None
        self.deterministic = True
        """Act with the policy's mean (SB3's ``deterministic=True``), as every evaluation does; False samples the
        policy's distribution as training does (``benchmarks/diagnose_sb3.py`` compares the two)."""

    # ---- building ----------------------------------------------------------------------------------------
    def algorithm_kwargs(self, horizon: int) -> dict:
        """SB3 constructor arguments from the settings (``horizon``: decisions per day)."""
        raise NotImplementedError

    def check_fit(self, horizon: int) -> None:
        """Settings checks that need the day's length."""

    def build_algorithm(self, venv: FleetVecEnv) -> BaseAlgorithm:
        """A fresh SB3 algorithm on ``venv``, seeded with the controller's seed."""
        return self.algorithm("MlpPolicy", venv, seed=self.seed, device=self.device, verbose=0,
                              **self.algorithm_kwargs(venv.horizon))

    def gradient_steps(self, model: BaseAlgorithm) -> int:
        """Optimizer steps of the policy so far."""
        return int(model._n_updates)

    def identity(self, train_core, day_ids) -> str:
        """What a checkpoint must match to resume (settings but the budget, seed, inputs, SB3 version)."""
        settings = {k: v for k, v in to_plain(self.options).items() if k not in RESUME_FREE}
        return stable_hash({"class": f"{type(self).__module__}:{type(self).__name__}", "settings": settings,
                            "seed": self.seed, "sb3": stable_baselines3.__version__,
                            "inputs": training_inputs_hash(train_core, day_ids)})

    def _meta(self, grid, scenario) -> dict:
        return {"method": self.name, "class": f"{type(self).__module__}:{type(self).__name__}",
                "algorithm": self.algorithm.__name__, "grid": {"rows": grid.rows, "cols": grid.cols},
                "n_uavs": scenario.n_uavs, "obs_dim": observation_dim(grid.rows, grid.cols, scenario),
                "scenario_hash": scenario.hash(), "demand_transform": DEMAND_TRANSFORM, "seed": self.seed}

    # ---- training ----------------------------------------------------------------------------------------
    def fit(self, train_core, *, run_dir, snapshots=None) -> dict:
        """Train on the TRAINING-days core; checkpoint under run_dir; return the training manifest.
        ``snapshots``: see ``Controller.fit`` (one is taken after the round that reaches each fraction)."""
        s = self.options
        run_dir = Path(run_dir)
        run_dir.mkdir(parents=True, exist_ok=True)
        horizon = train_core.scenario.slots_per_day - 1
        self.check_fit(horizon)
        venv = FleetVecEnv(train_core, n_envs=s.n_envs, seed=self.seed)
        ckpt = run_dir / CHECKPOINT
        identity = self.identity(train_core, venv.day_ids)
        rounds = s.day_episodes // s.n_envs
        self.meta = self._meta(train_core.grid, train_core.scenario)
        if snapshots is not None:
            snapshots.claim(ckpt)
        resumed = self._resume(ckpt, venv, identity, rounds)
        if resumed is None:
            model, writer, done = self.build_algorithm(venv), HistoryWriter(), 0
        else:
            model, writer, done = resumed
        model.set_logger(history_logger(writer))
        if snapshots is not None:
            snapshots.start(total=rounds, n_transitions=int(model.num_timesteps),
                            gradient_steps=self.gradient_steps(model),
                            write=lambda path: self._save_snapshot(path, model))
        every = max(1, math.ceil(rounds / MAX_HISTORY_POINTS))
        dumps = DumpEachUpdate(model._n_updates)
        for r in range(done, rounds):
            model.learn(total_timesteps=s.n_envs * horizon, callback=dumps, log_interval=None,
                        reset_num_timesteps=False, progress_bar=False)
            dumps.flush(model)
            if (r + 1) % every == 0 or r + 1 == rounds:
                ret, sr, n = venv.drain_finished()
                if n:
                    writer.write({"rollout/ep_rew_mean": ret, "rollout/ep_sr_mean": sr}, {}, model.num_timesteps)
                writer.point(model.num_timesteps)
            if snapshots is not None:
                snapshots.step(done=r + 1, total=rounds, n_transitions=int(model.num_timesteps),
                               gradient_steps=self.gradient_steps(model),
                               write=lambda path: self._save_snapshot(path, model))
            if (r + 1) % s.checkpoint_every == 0 or r + 1 == rounds:
                self._write_checkpoint(ckpt, model, venv, writer, r + 1, identity)
        if model.num_timesteps != horizon * len(venv.episodes) or len(venv.episodes) != s.day_episodes:
            raise RuntimeError(f"{self.name}: {model.num_timesteps} transitions over {len(venv.episodes)} finished "
                               f"day-episodes; expected {s.day_episodes} whole days of {horizon}")
        self.model = model
        days = venv.episode_days()
        return {"days": days, "day_labels": [train_core.day_labels[d] for d in venv.episodes],
                "transitions_per_day_episode": horizon, "n_transitions": horizon * len(days),
                "steps": self.gradient_steps(model), "checkpoint": str(ckpt),
                "checkpoint_written_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(ckpt.stat().st_mtime)),
                "read_test_data": False, "history": writer.history}

    def _write_checkpoint(self, path: Path, model: BaseAlgorithm, venv: FleetVecEnv, writer: HistoryWriter,
                          rounds_done: int, identity: str) -> None:
        state = {"identity": identity, "rounds_done": rounds_done, "rng": rng_states(model),
                 "env": venv.state_dict(), "history": writer.history}
        blob = io.BytesIO()
        torch.save(state, blob)
        with atomic_path(path) as tmp:
            self._save_zip(tmp, model)
            with zipfile.ZipFile(tmp, "a") as zf:
                zf.writestr(STATE_MEMBER, blob.getvalue())
                if getattr(model, "replay_buffer", None) is not None:
                    with zf.open(BUFFER_MEMBER, "w", force_zip64=True) as fh:
                        pickle.dump(model.replay_buffer, fh, protocol=pickle.HIGHEST_PROTOCOL)

    def _resume(self, path: Path, venv: FleetVecEnv, identity: str, rounds: int):
        """(model, writer, rounds done) from a matching checkpoint, else None (training starts afresh)."""
        if not path.is_file():
            return None
        try:
            with zipfile.ZipFile(path) as zf:
                state = torch.load(io.BytesIO(zf.read(STATE_MEMBER)), weights_only=False)
        except (zipfile.BadZipFile, KeyError, OSError, pickle.UnpicklingError, RuntimeError):
            return None
        if state.get("identity") != identity or state.get("rounds_done", rounds + 1) > rounds:
            return None
        with path.open("rb") as fh:
            model = self.algorithm.load(fh, env=venv, device=self.device, force_reset=False)
        if getattr(model, "replay_buffer", None) is not None:
            with zipfile.ZipFile(path) as zf, zf.open(BUFFER_MEMBER) as fh:
                model.replay_buffer = pickle.load(fh)
            model.replay_buffer.device = model.device
        obs = venv.load_state_dict(state["env"])
        if not np.array_equal(obs, model._last_obs):
            raise RuntimeError(f"{path}: the checkpoint's last observation does not match its round's days")
        set_rng_states(model, state["rng"])
        return model, HistoryWriter(state["history"]), int(state["rounds_done"])

    # ---- files -------------------------------------------------------------------------------------------
    def _save_zip(self, tmp: Path, model: BaseAlgorithm) -> None:
        with open(tmp, "wb") as fh:  # a file object: SB3 adds no ".zip" to it
            model.save(fh)
        with zipfile.ZipFile(tmp, "a") as zf:
            zf.writestr(META_MEMBER, json.dumps(self.meta, sort_keys=True))

    def _save_snapshot(self, path: Path, model: BaseAlgorithm) -> None:
        """The model file of ``model`` in training (:meth:`save`'s format), written atomically at ``path``."""
        with atomic_path(path) as tmp:
            self._save_zip(tmp, model)

    def save(self, path) -> None:
        """SB3's zip of the trained algorithm plus ``dswm/meta.json``, written atomically at ``path`` as named."""
        if self.model is None:
            raise RuntimeError(f"{self.name}: nothing to save, the model is not trained")
        with atomic_path(path) as tmp:
            self._save_zip(tmp, self.model)

    def load(self, path) -> None:
        """Read what :meth:`save` (or a checkpoint) wrote; the process's RNG states are left as they were."""
        path = Path(path)
        try:
            with zipfile.ZipFile(path) as zf:
                meta = json.loads(zf.read(META_MEMBER))
        except (zipfile.BadZipFile, KeyError) as err:
            raise ValueError(f"{path}: not a {self.name} model file (expected an SB3 zip with {META_MEMBER})") from err
        if meta.get("algorithm") != self.algorithm.__name__:
            raise ValueError(f"{path}: a {meta.get('algorithm')} model, expected {self.algorithm.__name__}")
        states = (random.getstate(), np.random.get_state(), torch.get_rng_state())
        with path.open("rb") as fh:
            self.model = self.algorithm.load(fh, device=self.device)
        random.setstate(states[0])
        np.random.set_state(states[1])
        torch.set_rng_state(states[2])
        self.meta = meta

    # ---- acting ------------------------------------------------------------------------------------------
    def reset_batch(self, ctxs: Sequence[DayContext]) -> None:
        if self.model is None:
            raise RuntimeError(f"{self.name}: reset_batch() before fit() or load()")
        for ctx in ctxs:
            g, sc = ctx.grid, ctx.scenario
            if (g.rows, g.cols) != (self.meta["grid"]["rows"], self.meta["grid"]["cols"]):
                raise ValueError(f"{self.name}: model trained on a {self.meta['grid']['rows']}x"
                                 f"{self.meta['grid']['cols']} grid, day {ctx.label} of {ctx.dataset} has "
                                 f"{g.rows}x{g.cols}")
            if sc.hash() != self.meta["scenario_hash"]:
                raise ValueError(f"{self.name}: model trained under scenario hash {self.meta['scenario_hash']}, day "
                                 f"{ctx.label} of {ctx.dataset} is evaluated under {sc.hash()}; retrain it")

    def reset(self, ctx: DayContext) -> None:
        self.reset_batch([ctx])

    def act_batch(self, obs: Mapping[str, Any]) -> np.ndarray:
        """(B, K, 3): the policy's action on the flat observation (its mean unless ``deterministic`` is False),
        clipped to [-1, 1]."""
        flat = flat_observation(obs)
        action, _ = self.model.predict(flat, deterministic=self.deterministic)
        return np.clip(fleet_action(action, self.meta["n_uavs"]), -1.0, 1.0)

    def act(self, obs: Mapping[str, Any]) -> np.ndarray:
        return self.act_batch({k: np.asarray(v)[None] for k, v in obs.items()})[0]


class PPOController(SB3Controller):
    """SB3's PPO with a Gaussian MLP policy and an MLP value function."""

    algorithm = PPO
    options_type = PPOSettings

    def check_fit(self, horizon: int) -> None:
        self.options.rollout_check(horizon)

    def algorithm_kwargs(self, horizon: int) -> dict:
        return self.options.ppo_kwargs(horizon)

    def gradient_steps(self, model: BaseAlgorithm) -> int:
        """SB3 counts epochs in ``_n_updates``; each epoch is rollout / batch_size minibatch steps."""
        s = self.options
        return int(model._n_updates) * (model.n_steps * s.n_envs // s.batch_size)


class SACController(SB3Controller):
    """SB3's SAC with a squashed-Gaussian MLP actor and two MLP critics (its gradient step made leaner:
    :mod:`dswm.methods.rl.sac_train`)."""

    algorithm = SAC
    options_type = SACSettings

    def algorithm_kwargs(self, horizon: int) -> dict:
        s = self.options
        arch = list(s.net_arch)
        return {"learning_rate": s.learning_rate, "buffer_size": s.buffer_size, "learning_starts": s.learning_starts,
                "batch_size": s.batch_size, "tau": s.tau, "gamma": s.gamma, "train_freq": (s.train_freq, "step"),
                "gradient_steps": s.gradient_steps,
                "ent_coef": f"auto_{s.ent_coef_init}" if s.auto_entropy else s.ent_coef_init,
                "optimize_memory_usage": False, "replay_buffer_class": ReplayBuffer,
                "replay_buffer_kwargs": {"handle_timeout_termination": True, "observation_dtype": s.matmul_dtype},
                "matmul_dtype": s.matmul_dtype,
                "policy_kwargs": {"net_arch": {"pi": arch, "qf": list(arch)}, "optimizer_kwargs": {"fused": True}}}
