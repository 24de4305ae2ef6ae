"""Steady-state rates of each learner's OWN training loop, measured inside its real ``fit``.

A learner's ``fit(core, run_dir=, snapshots=)`` calls ``snapshots.step(done=, total=, n_transitions=, write=)``
after every unit of its budget (a round, a day-episode, a gradient step, a task: ``dswm.methods.snapshots``). The
:class:`Recorder` stands in for those snapshots: it takes no snapshot, it notes when each unit ends and how many
environment transitions the run has consumed, and once enough units are timed it raises :class:`Enough`, which
ends the fit there. It can also time every ``FleetCore.step`` of the training core (the environment part of a loop
whose unit is a gradient step: pre-collection, TD-MPC's own episodes).

A unit's time is from the end of the previous unit to the end of this one: the learner's environment steps, its
updates and its bookkeeping, without the snapshot machinery; checkpoints are moved out of the timed units
(``checkpoint_every`` past the timed budget) and the run's set-up and first units are its warm-up. Each probe
changes only budget keys (how long the run is, when learning starts, when checkpoints are written), never a
network, batch, epoch or planner size; the changes are recorded beside the result as ``timing_changes``.
"""
from __future__ import annotations

import dataclasses
import math
import tempfile
import time
from pathlib import Path
from typing import Any, Callable, Mapping

import torch

from _timing import rate, spread

NEVER = 10**9
"""A checkpoint interval past any timed budget: no checkpoint lands in a timed unit."""


@dataclasses.dataclass(frozen=True)
class Counts:
    """How many units a probe times."""

    warmup: int
    """Units run before timing (set-up, first allocations, the first update)."""
    repeats: int
    """Timed repeats (>= 5): the median and the spread are over these."""
    group: int = 1
    """Units per repeat (short units, e.g. one gradient step, are summed in groups)."""

    @property
    def units(self) -> int:
        return self.warmup + self.repeats * self.group


class Enough(Exception):
    """Raised by the recorder once its units are timed: ends the fit early (nothing after it is measured)."""


class Recorder:
    """The ``snapshots`` a probe passes to ``fit``: times each unit, takes no snapshot.

    Args:
        stop_after: raise :class:`Enough` at this unit (None: let the fit run to its end).
        at_units: {unit: hook(write)} called inside the unit's ``step`` (outside every timed interval) with the
            fit's snapshot writer, e.g. to read the learner's gradient-step counter.
    """

    def __init__(self, *, stop_after: int | None, at_units: Mapping[int, Callable] | None = None):
        self.stop_after = stop_after
        self.at_units = dict(at_units or {})
        self.t0 = time.perf_counter()
        self.unit_end: list[float] = []      # when each unit's step() was entered
        self.unit_left: list[float] = []     # when it returned (the next unit starts then)
        self.transitions: list[int] = []
        self.env: list[tuple[float, int]] = []  # (start time, batch) of every FleetCore.step of the wrapped core
        self.env_stop: Callable[["Recorder"], bool] | None = None
        self.controller = None               # the controller in training (set by :func:`run_fit`)

    # ---- the snapshots interface -------------------------------------------------------------------------
    def claim(self, checkpoint) -> None:
        """Nothing to claim: the probe runs in a fresh directory."""

    def start(self, *, total: int, n_transitions: int, write, gradient_steps: int | None = 0) -> list[float]:
        """No untrained snapshot: the probe times the updates only."""
        return []

    def step(self, *, done: int, total: int, n_transitions: int, write,
             gradient_steps: int | None = None) -> list[float]:
        self.unit_end.append(time.perf_counter())
        self.transitions.append(int(n_transitions))
        hook = self.at_units.get(len(self.unit_end))
        if hook is not None:
            hook(write)
        self.unit_left.append(time.perf_counter())
        if self.stop_after is not None and len(self.unit_end) >= self.stop_after:
            raise Enough
        return []

    # ---- the environment ---------------------------------------------------------------------------------
    def wrap(self, core) -> None:
        """Time every ``core.step`` (its start and batch); :attr:`env_stop` may end the fit there."""
        inner = core.step

        def step(actions, *args, **kwargs):
            self.env.append((time.perf_counter(), int(len(actions))))
            if self.env_stop is not None and self.env_stop(self):
                raise Enough
            return inner(actions, *args, **kwargs)

        core.step = step

    # ---- what was measured -------------------------------------------------------------------------------
    def unit_times(self) -> list[float]:
        """Seconds of every unit recorded (the first from the recorder's creation: set-up included)."""
        starts = [self.t0, *self.unit_left[:-1]]
        return [end - start for start, end in zip(starts, self.unit_end)]

    def env_intervals(self, first: int, last: int) -> list[tuple[float, int]]:
        """(seconds to the next step's start, batch) of env steps ``first..last-1``: decision + step + storing."""
        ev = self.env
        return [(ev[i + 1][0] - ev[i][0], ev[i][1]) for i in range(first, min(last, len(ev) - 1))]


def grouped(times: list[float], counts: Counts, skip: int = 0) -> tuple[list[float], list[float]]:
    """(warm-up times, timed repeats): ``skip`` ramp units and ``counts.warmup`` units first, then sums of
    ``counts.group`` units, ``counts.repeats`` of them."""
    head = skip + counts.warmup
    body = times[head:head + counts.repeats * counts.group]
    if len(body) < counts.repeats * counts.group:
        raise RuntimeError(f"expected {counts.repeats * counts.group} timed units after {head}, found {len(body)}")
    g = counts.group
    return times[:head], [sum(body[i:i + g]) for i in range(0, len(body), g)]


def phase(repeat_times: list[float], *, warmup: int, transitions: float, steps: float | None) -> dict:
    """One measured phase: seconds per repeat, the work of a repeat and the rates at the median and the spread."""
    timing = spread(repeat_times, warmup=warmup)
    out = {"seconds_per_repeat": timing, "transitions_per_repeat": transitions,
           "transitions_per_second": rate(timing, transitions) if transitions else None,
           "gradient_steps_per_repeat": steps,
           "gradient_steps_per_second": rate(timing, steps) if steps else None}
    return out


def changed(options: Any, changes: Mapping[str, Any]) -> Any:
    """``options`` with ``changes`` (nested mappings change nested settings), rebuilt and so re-validated."""
    fields = {}
    for key, value in changes.items():
        current = getattr(options, key)
        fields[key] = changed(current, value) if isinstance(value, Mapping) and dataclasses.is_dataclass(current) \
            else value
    return dataclasses.replace(options, **fields)


def run_fit(cls, name: str, options: Any, core, recorder: Recorder, seed: int = 0) -> dict | None:
    """``fit`` of a fresh controller on ``core`` in a temporary run directory, as a train job builds it (torch
    seeded first); the manifest, or None when the recorder ended it early."""
    torch.manual_seed(seed)
    ctl = recorder.controller = cls(name=name, seed=seed, device="cpu", options=options)
    with tempfile.TemporaryDirectory(prefix=f"bench-{name}-") as run_dir:
        recorder.t0 = time.perf_counter()
        try:
            return ctl.fit(core, run_dir=run_dir, snapshots=recorder)
        except Enough:
            return None


# ---- the probes -----------------------------------------------------------------------------------------
DAY = 143
"""Decisions (transitions) per day-episode: slots_per_day - 1."""


def rounds_probe(name: str, cls, options, core, counts: Counts, *, changes: dict, per_unit_steps=None,
                 ramp: int = 0, counter: Callable | None = None) -> dict:
    """A learner whose unit is a round, a day-episode or a task: units timed whole.

    Args:
        changes: budget changes (recorded); per_unit_steps: gradient steps per unit from the settings, or None to
            read the learner's own counter (``counter(controller)``) at the first and the last timed unit;
        ramp: units at the start without the steady state's updates (a replay filling to one batch).
    """
    timed_options = changed(options, changes)
    marks: dict[int, int] = {}
    first, last = ramp + counts.warmup, ramp + counts.units
    with tempfile.TemporaryDirectory(prefix=f"bench-{name}-marks-") as scratch:
        def mark(unit: int) -> Callable:
            def hook(write) -> None:   # the fit's snapshot writer hands the live learner to the controller
                write(Path(scratch) / f"unit{unit}.pt")
                marks[unit] = int(counter(rec.controller))
            return hook

        hooks = {first: mark(first), last: mark(last)} if per_unit_steps is None else {}
        rec = Recorder(stop_after=last, at_units=hooks)
        run_fit(cls, name, timed_options, core, rec)
    times = rec.unit_times()
    warm, reps = grouped(times, counts, skip=ramp)
    tr = rec.transitions
    per_unit_transitions = (tr[last - 1] - tr[first - 1]) / (last - first)
    if per_unit_steps is None:
        per_unit_steps = (marks[last] - marks[first]) / (last - first)
    g = counts.group
    return {"timing_changes": changes, "ramp_units": ramp,
            "train": phase(reps, warmup=len(warm), transitions=per_unit_transitions * g, steps=per_unit_steps * g)}


def sb3_probe(name, cls, options, core, counts: Counts, *, extra: dict | None = None) -> dict:
    """PPO or SAC: a unit is a round of n_envs day-episodes (one ``learn`` call)."""
    changes = {"day_episodes": options.n_envs * counts.units, "checkpoint_every": NEVER, **(extra or {})}
    if name == "ppo":   # PPOController.gradient_steps: each epoch is rollout / batch_size minibatch steps
        steps = options.n_epochs * (options.n_envs * DAY // options.batch_size)
    else:               # SAC: gradient_steps after each of the round's 143 vectorized steps (train_freq 1)
        steps = (DAY // options.train_freq) * options.gradient_steps
    return rounds_probe(name, cls, options, core, counts, changes=changes, per_unit_steps=steps)


def trained_probe(name, cls, options, core, counts: Counts, *, changes: dict, ramp: int = 0) -> dict:
    """MADDPG, GA-MATR, HRL-TPRA (``dswm.methods.trained``): gradient steps from the learner's own counter."""
    return rounds_probe(name, cls, options, core, counts, changes=changes, ramp=ramp,
                        counter=lambda ctl: ctl.learner.steps)


def emorl_probe(name, cls, options, core, counts: Counts) -> dict:
    """EMORL-TCTO: a unit is a task (task_rounds PPO rounds of its policy, then its measurement on eval_days
    training days); the warm-up generation's tasks are given the generations' task_rounds."""
    n_pop = options.n_population
    changes = {"warmup_rounds": options.task_rounds, "generations": max(0, math.ceil(counts.units / n_pop) - 1),
               "checkpoint_every": NEVER}
    steps = options.task_rounds * options.n_epochs * (options.n_envs * DAY // options.batch_size)
    return rounds_probe(name, cls, options, core, counts, changes=changes, per_unit_steps=steps)


def step_probe(name, cls, options, core, counts: Counts, *, changes: dict, play: Counts | None = None) -> dict:
    """DSWM's world model and TD-MPC: a unit is a gradient step. The pre-collection (the core's steps before the
    first gradient step) is timed per core step; with ``play``, TD-MPC's own episodes after the seed phase too
    (per core step: MPPI on the round's days, the step and storing), after which the fit ends."""
    timed_options = changed(options, changes)
    n_steps = counts.units
    rec = Recorder(stop_after=None if play else n_steps)
    n_pre_env = [0]   # core steps before the first gradient step: the pre-collection
    if play is not None:
        rec.env_stop = lambda r: len(r.unit_end) >= n_steps and len(r.env) > n_pre_env[0] + play.units + 1
    rec.wrap(core)
    orig_step = rec.step

    def step(**kw):
        if not rec.unit_end:
            n_pre_env[0] = len(rec.env)
        return orig_step(**kw)

    rec.step = step
    try:
        run_fit(cls, name, timed_options, core, rec)
    finally:
        del core.step   # the core's own step again
    warm, reps = grouped(rec.unit_times(), counts)
    out = {"timing_changes": changes,
           "gradient": phase(reps, warmup=len(warm), transitions=0, steps=counts.group)}
    collect = rec.env_intervals(0, n_pre_env[0])
    if len(collect) >= 5 + 1:
        cw, cr = collect[:1], collect[1:]
        out["collect"] = phase([t for t, _ in cr], warmup=len(cw), transitions=cr[0][1], steps=None)
    if play is not None:
        ev = rec.env_intervals(n_pre_env[0], len(rec.env))
        w, r = grouped([t for t, _ in ev], play)
        out["play"] = phase(r, warmup=len(w), transitions=ev[0][1] * play.group, steps=None)
    return out
