"""The EMORL-TCTO controller: ``fit`` runs the evolution on the training core; the executed policy is the archive
member the ``select_rule`` names, acting deterministically on B days at once."""
from __future__ import annotations

import pickle
import time
from pathlib import Path
from typing import Any, ClassVar, Mapping, Sequence

import numpy as np
import stable_baselines3
import torch

from dswm.config import stable_hash, to_plain
from dswm.methods.base import Controller, DayContext, training_inputs_hash
from dswm.methods.emorl_tcto.archive import OBJECTIVES, non_dominated, select_member
from dswm.methods.emorl_tcto.objectives import make_policy, policy_actions
from dswm.methods.emorl_tcto.settings import RESUME_FREE, EMORLTCTOSettings
from dswm.methods.emorl_tcto.training import Evolution
from dswm.methods.rl.spaces import DEMAND_TRANSFORM, observation_dim
from dswm.sim.core import Grid
from prep.atomic import atomic_path

CHECKPOINT = "checkpoint.pt"
FORMAT = "emorl_tcto/1"
"""Tag of the model file."""


class EMORLTCTOController(Controller):
    """EMORL-TCTO (Song et al. 2022), re-implemented in the style of PGMORL (Xu et al. 2020): a population of
    SB3 PPO policies on weighted objectives (served ratio, energy, fairness), evolved by prediction-guided tasks
    into a Pareto archive; the archive member named by ``select_rule`` is executed.

    The model file holds every archive member's policy, so the rule is a decision-time setting (a different rule
    retrains nothing: :meth:`training_settings` leaves it out).
    """

    learns: ClassVar[bool] = True
    batched: ClassVar[bool] = True
    shares_training: ClassVar[bool] = True
    options_type: ClassVar[type] = EMORLTCTOSettings

    def __init__(self, *, name: str, seed: int = 0, device: str = "cpu", options: EMORLTCTOSettings):
        super().__init__(name=name, seed=seed, device=device, options=options)
        self.archive: list[dict] | None = None
        self.meta: dict | None = None
        self.scenario = None
        self.policy = None
        self.selected: int | None = None
        self._days = 0

    @property
    def settings(self) -> EMORLTCTOSettings:
        return self.options

    @classmethod
    def training_settings(cls, options: EMORLTCTOSettings) -> EMORLTCTOSettings:
        """Everything but the executed member's rule (``select_rule``, ``select_weight``)."""
        return options.training()

    def identity(self, train_core) -> str:
        """What a checkpoint must match to resume: class, seed, training settings but the budget, SB3's version,
        the training inputs."""
        settings = {k: v for k, v in to_plain(self.training_settings(self.settings)).items() if k not in RESUME_FREE}
        return stable_hash({"class": f"{type(self).__module__}:{type(self).__name__}", "settings": settings,
                            "seed": self.seed, "sb3": stable_baselines3.__version__,
                            "inputs": training_inputs_hash(train_core)})

    # ---- training ----------------------------------------------------------------------------------------
    def fit(self, train_core, *, run_dir, snapshots=None) -> dict:
        """Run (or resume) the evolution on the TRAINING-days core; checkpoint between tasks; return the manifest.

        The manifest's days are every day-episode run, in order: each task's training rounds, then each
        policy's measurement on the evaluation days. ``snapshots``: see ``Controller.fit`` (the budget is the
        tasks; a snapshot holds the archive the generation would end with if it ended there).
        """
        run_dir = Path(run_dir)
        run_dir.mkdir(parents=True, exist_ok=True)
        evo = Evolution(core=train_core, settings=self.settings, seed=self.seed, device=self.device)
        ckpt, identity = run_dir / CHECKPOINT, self.identity(train_core)

        def write_snapshot(path: Path) -> None:
            self._keep(evo, train_core, with_pending=True)
            self.save(path)

        if snapshots is not None:
            snapshots.claim(ckpt)
        state = self._checkpoint(ckpt)
        if state is not None and state.get("identity") == identity and state["tasks_done"] <= evo.total_tasks():
            evo.load_state_dict(state)  # the same run, interrupted or shorter: continue it
        del state
        if snapshots is not None:
            def write_initial(path: Path) -> None:
                self._keep_initial(evo, train_core)
                self.save(path)

            snapshots.start(total=evo.total_tasks(), n_transitions=evo.horizon * len(evo.day_log),
                            gradient_steps=evo.gradient_steps(), write=write_initial)
        every = self.settings.checkpoint_every
        while not evo.finished():
            evo.run_task()
            if snapshots is not None:
                snapshots.step(done=evo.tasks_done, total=evo.total_tasks(), gradient_steps=evo.gradient_steps(),
                               n_transitions=evo.horizon * len(evo.day_log), write=write_snapshot)
            if evo.tasks_done % every == 0 or evo.finished():
                evo.save(ckpt, identity)
        evo.check_record()
        self._keep(evo, train_core)
        ids = evo.venv.day_ids
        days = [int(ids[d]) for d in evo.day_log]
        return {"days": days, "day_labels": [train_core.day_labels[d] for d in evo.day_log],
                "transitions_per_day_episode": evo.horizon, "n_transitions": evo.horizon * len(days),
                "steps": evo.gradient_steps(), "checkpoint": str(ckpt),
                "checkpoint_written_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(ckpt.stat().st_mtime)),
                "read_test_data": False, "history": evo.writer.history}

    @staticmethod
    def _checkpoint(path: Path) -> dict | None:
        """The checkpoint's state, or None when there is none or it cannot be read (training starts afresh)."""
        if not path.is_file():
            return None
        try:
            state = torch.load(path, map_location="cpu", weights_only=False)  # RNG states live on the CPU
        except (OSError, EOFError, RuntimeError, pickle.UnpicklingError):
            return None
        return state if isinstance(state, dict) and "tasks_done" in state else None

    def _keep(self, evo: Evolution, core, *, with_pending: bool = False) -> None:
        """The archive's policies (weights only) and what acting needs, from a finished evolution; with
        ``with_pending``, from one in progress: the non-dominated members of the archive and the current
        generation's children so far (the archive the generation would end with if it ended now; ``evo`` is
        left as it was)."""
        members = evo.archive
        if with_pending:
            candidates = evo.archive + evo.pending
            members = [candidates[i] for i in non_dominated(np.stack([evo.members[m].objectives
                                                                      for m in candidates]))]
        self._keep_archive(evo, core, [{"id": m.id, "parent": m.parent, "generation": m.generation,
                                        "weight": [float(x) for x in m.weight],
                                        "objectives": [float(x) for x in m.objectives],
                                        "policy": {k: v.detach().cpu().clone() for k, v in m.params["policy"].items()}}
                                       for m in (evo.members[i] for i in members)])

    def _keep_initial(self, evo: Evolution, core) -> None:
        """The untrained model (the learning curves' first point): an archive of the one policy the evolution's
        worker holds before its first task, unmeasured (objectives 0), so that the select rule executes it."""
        policy = evo.worker.policy.state_dict()
        self._keep_archive(evo, core, [{"id": -1, "parent": None, "generation": -1, "weight": [0.0] * len(OBJECTIVES),
                                        "objectives": [0.0] * len(OBJECTIVES),
                                        "policy": {k: v.detach().cpu().clone() for k, v in policy.items()}}])

    def _keep_archive(self, evo: Evolution, core, archive: list[dict]) -> None:
        """Keep ``archive`` (the model file's members) with what acting needs, and build the selected policy."""
        self.archive = archive
        ids = evo.venv.day_ids
        s, grid, sc = self.settings, core.grid, core.scenario
        self.scenario = sc
        self.meta = {"format": FORMAT, "method": self.name, "seed": self.seed,
                     "grid": {"rows": grid.rows, "cols": grid.cols, "cell_m": grid.cell_m}, "n_uavs": sc.n_uavs,
                     "obs_dim": observation_dim(grid.rows, grid.cols, sc), "scenario_hash": sc.hash(),
                     "demand_transform": DEMAND_TRANSFORM, "net_arch": list(s.net_arch),
                     "log_std_init": s.log_std_init, "objectives": list(OBJECTIVES),
                     "eval_days": [int(ids[d]) for d in evo.eval_days]}
        self._select()

    def _select(self) -> None:
        """Build the policy of the member the select rule names (none without a rule: a training slice)."""
        s = self.settings
        self.policy, self.selected = None, None
        if s.select_rule is None:
            return
        row = select_member(np.array([m["objectives"] for m in self.archive]), s.select_rule, s.select_weight)
        grid = Grid(**self.meta["grid"])
        with torch.random.fork_rng(devices=[]):  # building the networks leaves the process's RNGs alone
            policy = make_policy(grid, self.scenario, net_arch=self.meta["net_arch"],
                                 log_std_init=self.meta["log_std_init"], learning_rate=s.learning_rate,
                                 device=self.device)
        policy.load_state_dict(self.archive[row]["policy"])
        policy.set_training_mode(False)
        self.policy, self.selected = policy, row

    # ---- model file --------------------------------------------------------------------------------------
    def save(self, path) -> None:
        """Every archive member (id, lineage, weight, objectives, policy weights), the scenario and what acting
        checks; one torch file written atomically."""
        if self.archive is None:
            raise RuntimeError(f"{self.name}: nothing to save, the model is not trained")
        blob = {"meta": self.meta, "scenario": self.scenario, "archive": self.archive}
        with atomic_path(path) as tmp:
            torch.save(blob, tmp)

    def load(self, path) -> None:
        """Read what :meth:`save` wrote and build the member the select rule names."""
        blob = torch.load(path, map_location="cpu", weights_only=False)
        if not isinstance(blob, dict) or blob.get("meta", {}).get("format") != FORMAT:
            raise ValueError(f"{path}: not an EMORL-TCTO model file (expected meta.format {FORMAT!r})")
        if blob["meta"]["net_arch"] != list(self.settings.net_arch):
            raise ValueError(f"{path}: networks of widths {blob['meta']['net_arch']}; methods.{self.name} expects "
                             f"{list(self.settings.net_arch)}; retrain it")
        self.meta, self.scenario, self.archive = blob["meta"], blob["scenario"], blob["archive"]
        self._select()

    # ---- acting ------------------------------------------------------------------------------------------
    def reset_batch(self, ctxs: Sequence[DayContext]) -> None:
        """Check that every day is on the grid and under the scenario the archive was trained on."""
        if self.archive is None:
            raise RuntimeError(f"{self.name}: reset before fit() or load()")
        if self.policy is None:
            raise RuntimeError(f"{self.name}: no select_rule in methods.{self.name}: the executed member is unknown")
        g = self.meta["grid"]
        self._days = len(ctxs)
        for ctx in ctxs:
            if (ctx.grid.rows, ctx.grid.cols) != (g["rows"], g["cols"]):
                raise ValueError(f"{self.name}: model trained on a {g['rows']}x{g['cols']} grid, day {ctx.label} of "
                                 f"{ctx.dataset} has {ctx.grid.rows}x{ctx.grid.cols}")
            if ctx.scenario.hash() != self.meta["scenario_hash"]:
                raise ValueError(f"{self.name}: model trained under scenario hash {self.meta['scenario_hash']}, day "
                                 f"{ctx.label} of {ctx.dataset} is evaluated under {ctx.scenario.hash()}; retrain it")

    def act_batch(self, obs: Mapping[str, Any]) -> np.ndarray:
        """(B, K, 3) float32: the executed member's deterministic action on the flat observation, in [-1, 1]."""
        return policy_actions(self.policy, obs, self.meta["n_uavs"])

    def reset(self, ctx: DayContext) -> None:
        self.reset_batch([ctx])

    def act(self, obs: Mapping[str, Any]) -> np.ndarray:
        return self.act_batch({k: np.asarray(v)[None] for k, v in obs.items()})[0]

    def day_stats(self) -> list[dict[str, float]]:
        """The executed member's id (one value per day of the last reset; the same member every day)."""
        return [{"member": float(self.archive[self.selected]["id"])} for _ in range(self._days)]
