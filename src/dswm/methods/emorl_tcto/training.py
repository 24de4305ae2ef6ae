"""EMORL-TCTO's evolution: a warm-up population of PPO policies, then generations of prediction-guided tasks, a
Pareto archive, and complete checkpoints between tasks.

* Warm-up (generation 0): ``n_population`` fresh policies (independent initializations) are measured, then each
  is trained for ``warmup_rounds`` PPO rounds on one of the evenly spread weights (``archive.warmup_weights``).
* Generation g >= 1: the tasks (parent, weight) are chosen by prediction (``prediction.select_tasks``) among the
  archive members and the weight lattice; each task loads its parent's policy AND optimizer state into the one
  SB3 PPO learner, sets the environment's weight, and continues training for ``task_rounds`` rounds. The trained
  policy is a new member (the parent stays as it was).
* After each generation the archive becomes the non-dominated members of (archive + the generation's children);
  only archive members keep their weights.
* Objective vectors: every member is measured once, acting deterministically on ``eval_days`` fixed TRAINING
  days (drawn from the seed) in a second core over the same days, so members compare on the same days.

The learner is SB3's PPO on :class:`.objectives.ObjectiveVecEnv`: one round is one rollout of n_envs whole
training days; rounds continue across tasks (the environment is not reset when the task changes). Every
day-episode run, training or measurement, is recorded in order (:attr:`Evolution.day_log`).
"""
from __future__ import annotations

import copy
import dataclasses
import math
from pathlib import Path
from typing import Any

import numpy as np
import torch
from stable_baselines3 import PPO

from dswm.methods.emorl_tcto.archive import (hypervolume, non_dominated, reference_point, warmup_weights,
                                             weight_lattice)
from dswm.methods.emorl_tcto.objectives import (ObjectiveVecEnv, evaluation_core, make_policy, max_energy_ratio,
                                                measure_objectives)
from dswm.methods.emorl_tcto.prediction import fit_improvement, neighbour_weights, select_tasks
from dswm.methods.emorl_tcto.settings import EMORLTCTOSettings
from dswm.methods.rl.common import DumpEachUpdate, rng_states, set_rng_states
from dswm.methods.rl.logger import HistoryWriter, history_logger
from prep.atomic import atomic_path

MAX_HISTORY_POINTS = 200
"""Round points of the training history at most (plus one at the end of every task)."""
EVAL_STREAM = 7
"""Stream of the seed's draws that picks the evaluation days."""
INIT_STREAM = 11
"""Stream of the seed's draws that initializes the warm-up policies."""


def initial_policy(core, settings: EMORLTCTOSettings, seed: int, index: int, device: str = "cpu"):
    """The ``index``-th fresh policy of the warm-up of run ``seed`` (its own torch stream; the process's torch RNG
    is left as it was)."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(int(np.random.SeedSequence([seed, INIT_STREAM, index]).generate_state(1)[0]))
        return make_policy(core, core.scenario, net_arch=settings.net_arch, log_std_init=settings.log_std_init,
                           learning_rate=settings.learning_rate, device=device)


@dataclasses.dataclass
class Member:
    """A policy of the population: where it came from, its measured objective vector and its weights."""

    id: int
    parent: int | None
    """Id of the policy it was trained from (None: a fresh initial policy)."""
    weight: np.ndarray | None
    """(3,) the weight of the task that produced it (None for an initial policy)."""
    objectives: np.ndarray
    """(3,) served ratio, -energy / (E_hover K), Jain index: means over the evaluation days."""
    generation: int
    """-1 initial, 0 warm-up, g >= 1 the generation of its task."""
    params: dict | None
    """SB3 parameters {"policy": state dict, "policy.optimizer": state dict}; None once out of the archive."""


class Evolution:
    """The whole training state of EMORL-TCTO on a core of TRAINING days.

    Args:
        core: the FleetCore of the training days (``core.day_ids``: their tensor days).
        settings: the method's settings; seed: the run's seed; device: torch device of the networks.
    """

    def __init__(self, *, core, settings: EMORLTCTOSettings, seed: int, device: str = "cpu"):
        s = self.settings = settings
        self.seed, self.device, self.core = seed, device, core
        self.horizon = core.scenario.slots_per_day - 1
        s.rollout_check(self.horizon)
        self.venv = ObjectiveVecEnv(core, n_envs=s.n_envs, seed=seed)
        self.eval_core = evaluation_core(core)
        draw = np.random.default_rng([seed, EVAL_STREAM])
        self.eval_days = sorted(draw.choice(core.n_days, size=min(s.eval_days, core.n_days), replace=False).tolist())
        self.worker = PPO("MlpPolicy", self.venv, seed=seed, device=device, verbose=0, **s.ppo_kwargs(self.horizon))
        self.writer = HistoryWriter()
        self.worker.set_logger(history_logger(self.writer))
        self.dumps = DumpEachUpdate(self.worker._n_updates)
        self.lattice = weight_lattice(s.weight_divisions)
        self.ref = reference_point(max_energy_ratio(core.scenario))
        total_rounds = s.n_population * (s.warmup_rounds + s.generations * s.task_rounds)
        self.point_every = max(1, math.ceil(total_rounds / MAX_HISTORY_POINTS))
        self.members: dict[int, Member] = {}
        self.archive: list[int] = []
        """Ids of the non-dominated members, oldest first."""
        self.tasks: list[tuple[int, np.ndarray, np.ndarray]] = []
        """Every task done: (parent id, weight, objective change of the child over the parent)."""
        self.plan: list[tuple[int, np.ndarray, np.ndarray | None]] = []
        """Tasks of the current generation still to train: (parent id, weight, predicted objectives or None)."""
        self.pending: list[int] = []
        """Children of the current generation so far (they join the archive when it ends)."""
        self.generation = -1
        self.tasks_done = 0
        self.rounds_done = 0
        self.measured_episodes = 0
        self.day_log: list[int] = []
        """Core day of every day-episode run (training rounds and measurements), in the order run."""

    # ---- progress ----------------------------------------------------------------------------------------
    def total_tasks(self) -> int:
        """Tasks of the whole run: the warm-up's and every generation's, n_population each."""
        return self.settings.n_population * (1 + self.settings.generations)

    def finished(self) -> bool:
        return self.tasks_done >= self.total_tasks()

    def gradient_steps(self) -> int:
        """Optimizer steps so far (SB3 counts epochs in ``_n_updates``; each is rollout / batch_size steps)."""
        return int(self.worker._n_updates) * (self.settings.n_envs * self.horizon // self.settings.batch_size)

    # ---- measuring ---------------------------------------------------------------------------------------
    def measure(self, policy) -> np.ndarray:
        """(3,) objective vector of ``policy`` (deterministic) over the evaluation days; the days are recorded."""
        f = measure_objectives(policy, self.eval_core, self.eval_days)
        self.day_log.extend(self.eval_days)
        self.measured_episodes += len(self.eval_days)
        return f.mean(axis=0)

    # ---- planning ----------------------------------------------------------------------------------------
    def _new_member(self, **fields) -> Member:
        member = Member(id=len(self.members), **fields)
        self.members[member.id] = member
        return member

    def _plan_warmup(self) -> None:
        s = self.settings
        for i, weight in enumerate(warmup_weights(s.n_population, s.weight_divisions)):
            policy = initial_policy(self.core, s, self.seed, i, self.device)
            member = self._new_member(parent=None, weight=None, objectives=self.measure(policy), generation=-1,
                                      params={"policy": policy.state_dict(),
                                              "policy.optimizer": policy.optimizer.state_dict()})
            self.plan.append((member.id, weight, None))
        self.generation = 0

    def predictions(self) -> np.ndarray:
        """(A, W, 3) predicted objective vector of every archive member trained with every lattice weight."""
        s = self.settings
        measured = np.stack([m.objectives for m in self.members.values()])
        scale = measured.max(axis=0) - measured.min(axis=0)
        parents = np.stack([self.members[p].objectives for p, _, _ in self.tasks])
        weights = np.stack([w for _, w, _ in self.tasks])
        deltas = np.stack([d for _, _, d in self.tasks])
        out = []
        for mid in self.archive:
            f = self.members[mid].objectives
            k = neighbour_weights(parents, f, scale, s.prediction_bandwidth)
            model = fit_improvement(weights, deltas, s.prediction_ridge, sample_weight=k)
            out.append(f[None, :] + model.predict(self.lattice))
        return np.stack(out)

    def _plan_generation(self) -> None:
        f = np.stack([self.members[m].objectives for m in self.archive])
        chosen = select_tasks(f, self.predictions(), self.lattice, self.settings.n_population, self.ref)
        self.plan = [(self.archive[t.parent], self.lattice[t.weight].copy(), t.predicted) for t in chosen]
        self.generation += 1

    def _update_archive(self) -> None:
        candidates = self.archive + self.pending  # ids ascending: of identical vectors the older one stays
        keep = non_dominated(np.stack([self.members[m].objectives for m in candidates]))
        self.archive = [candidates[i] for i in keep]
        self.pending = []
        for member in self.members.values():
            if member.id not in self.archive:
                member.params = None

    def archive_hypervolume(self) -> float:
        return hypervolume(np.stack([self.members[m].objectives for m in self.archive]), self.ref) \
            if self.archive else float("nan")

    # ---- training ----------------------------------------------------------------------------------------
    def run_task(self) -> Member:
        """Plan the next generation if the current one is done, then train and measure its next task."""
        if not self.plan and self.generation < 0:
            self._plan_warmup()
        elif not self.plan:
            self._plan_generation()
        s, worker = self.settings, self.worker
        parent, weight, predicted = self.plan[0]
        rounds = s.warmup_rounds if self.generation == 0 else s.task_rounds
        worker.set_parameters(copy.deepcopy(self.members[parent].params), exact_match=True, device=self.device)
        self.venv.weight = np.asarray(weight, dtype=np.float64)
        first_episode = len(self.venv.episodes)
        for r in range(rounds):
            worker.learn(total_timesteps=s.n_envs * self.horizon, callback=self.dumps, log_interval=None,
                         reset_num_timesteps=False, progress_bar=False)
            self.dumps.flush(worker)
            self.rounds_done += 1
            if r < rounds - 1 and self.rounds_done % self.point_every == 0:
                self._point({})
        self.day_log.extend(self.venv.episodes[first_episode:])
        child = self._new_member(parent=parent, weight=np.asarray(weight, dtype=np.float64),
                                 objectives=self.measure(worker.policy), generation=self.generation,
                                 params=copy.deepcopy(worker.get_parameters()))
        self.tasks.append((parent, child.weight, child.objectives - self.members[parent].objectives))
        self.pending.append(child.id)
        self.plan.pop(0)
        self.tasks_done += 1
        if not self.plan:
            self._update_archive()
        extra = {f"rollout/task_{name}": float(v) for name, v in
                 zip(("served_ratio", "neg_energy", "jain"), child.objectives)}
        if predicted is not None:
            extra["rollout/prediction_error_sr"] = float(child.objectives[0] - predicted[0])  # measured - predicted
        extra["rollout/archive_size"] = float(len(self.archive))
        extra["rollout/archive_hypervolume"] = self.archive_hypervolume()
        self._point(extra)
        return child

    def _point(self, extra: dict[str, float]) -> None:
        ret, sr, n = self.venv.drain_finished()
        if n:
            extra = {"rollout/ep_rew_mean": ret, "rollout/ep_sr_mean": sr, **extra}
        self.writer.write({k: v for k, v in extra.items() if math.isfinite(v)}, {}, self.worker.num_timesteps)
        self.writer.point(self.worker.num_timesteps)

    # ---- checkpoints -------------------------------------------------------------------------------------
    def state_dict(self, identity: str) -> dict[str, Any]:
        """Everything that resumes the run exactly, taken between tasks."""
        return {"identity": identity, "tasks_done": self.tasks_done, "rounds_done": self.rounds_done,
                "generation": self.generation, "members": {k: dict(vars(m)) for k, m in self.members.items()},
                "archive": list(self.archive), "tasks": list(self.tasks), "plan": list(self.plan),
                "pending": list(self.pending), "day_log": list(self.day_log),
                "measured_episodes": self.measured_episodes, "eval_days": list(self.eval_days),
                "n_updates": int(self.worker._n_updates), "num_timesteps": int(self.worker.num_timesteps),
                "env": self.venv.state_dict(), "rng": rng_states(self.worker), "history": self.writer.history}

    def save(self, path: Path, identity: str) -> None:
        """Write :meth:`state_dict` atomically to ``path`` (torch's format)."""
        with atomic_path(path) as tmp:
            torch.save(self.state_dict(identity), tmp)

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Continue from :meth:`state_dict`: members, archive, plan, counters, the environment's round, RNGs."""
        if list(state["eval_days"]) != self.eval_days:
            raise RuntimeError("checkpoint: its evaluation days differ from this run's")
        self.tasks_done, self.rounds_done = int(state["tasks_done"]), int(state["rounds_done"])
        self.generation = int(state["generation"])
        self.members = {int(k): Member(**m) for k, m in state["members"].items()}
        self.archive, self.tasks, self.plan = list(state["archive"]), list(state["tasks"]), list(state["plan"])
        self.pending, self.day_log = list(state["pending"]), list(state["day_log"])
        self.measured_episodes = int(state["measured_episodes"])
        self.worker._n_updates, self.worker.num_timesteps = int(state["n_updates"]), int(state["num_timesteps"])
        self.worker._last_obs = self.venv.load_state_dict(state["env"])
        self.worker._last_episode_starts = np.ones(self.settings.n_envs, dtype=bool)
        set_rng_states(self.worker, state["rng"])
        self.writer = HistoryWriter(state["history"])
        self.worker.set_logger(history_logger(self.writer))
        self.dumps = DumpEachUpdate(self.worker._n_updates)

    def check_record(self) -> None:
        """Every transition taken belongs to a recorded day-episode (training rounds are whole days)."""
        expected = self.venv.transitions + self.horizon * self.measured_episodes
        if expected != self.horizon * len(self.day_log):
            raise RuntimeError(f"emorl_tcto: {expected} transitions over {len(self.day_log)} recorded day-episodes; "
                               f"expected whole days of {self.horizon}")
