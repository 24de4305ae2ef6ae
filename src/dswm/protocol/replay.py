"""Replay of an evaluation with what the controller saw and did recorded, one :class:`DayPlay` per day.

The replay runs the project's evaluation (``dswm.protocol.evaluation.evaluate``) unchanged, with the controller's
``reset``/``act`` wrapped to copy every observation and answered action; the same seed, controller and days give
the main evaluation's trajectory again. Any non-batched controller can be replayed; the DSWM world-model quality
(``dswm.methods.dswm.quality``, paper Fig. 12) reads the record.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Mapping

import numpy as np

from dswm.protocol import evaluation
from dswm.sim.core import core_from_tensor


@dataclasses.dataclass(frozen=True, kw_only=True)
class DayPlay:
    """One evaluated day as the controller played it (T slots, T - 1 decisions)."""

    day: int
    """Tensor day index."""
    label: str
    split: str
    demand: np.ndarray
    """(T, R, C) the realized maps x_0..x_{T-1}."""
    obs: list[dict[str, np.ndarray]]
    """o_0..o_{T-2}, each {demand (w+1, R, C), fleet (K, 7), time (2,)}."""
    actions: np.ndarray
    """(T-1, K, 3) a_0..a_{T-2} as the controller answered them."""
    sr: np.ndarray
    """(T,) realized SR_0..SR_{T-1} (SR_0: the initial deployment)."""


def replay(*, tensor, controller, scenario, seed: int, days: Mapping[str, list[int]], profile: str, device: str,
           progress_interval_s: float) -> tuple[list[DayPlay], Any]:
    """Evaluate ``controller`` on ``days`` (``dswm.protocol.evaluation.evaluate``, one day at a time) and record
    what it saw and did.

    Args:
        tensor: the prepared dataset; controller: a fitted non-batched controller; scenario: the evaluation's.
        days: {split: tensor day indices}, in the order the main evaluation ran them.
    Returns:
        (one :class:`DayPlay` per evaluated day, in order; the evaluation's ``EvalResult``).
    Raises:
        ValueError: the controller is batched (its observations are not seen one day at a time).
    """
    if controller.batched:
        raise ValueError(f"{controller.name}: a batched controller cannot be replayed one day at a time")
    seen: list[dict] = []
    reset, act = controller.reset, controller.act

    def recording_reset(ctx):
        seen.append({"ctx": ctx, "obs": [], "actions": []})
        return reset(ctx)

    def recording_act(obs):
        action = act(obs)
        seen[-1]["obs"].append({k: np.array(v, copy=True) for k, v in obs.items()})
        seen[-1]["actions"].append(np.array(action, dtype=np.float32, copy=True))
        return action

    controller.reset, controller.act = recording_reset, recording_act
    try:
        result = evaluation.evaluate(tensor=tensor, controller=controller, scenario=scenario, seed=seed,
                                     limits={"id": None, "ood": None}, profile=profile, device=device,
                                     batch_days=False, progress_interval_s=progress_interval_s, trajectory=False,
                                     days=days)
    finally:
        del controller.reset, controller.act  # the class's methods again
    plays = []
    for rec in seen:
        ctx = rec["ctx"]
        actions = np.stack(rec["actions"])
        plays.append(DayPlay(day=int(ctx.day), label=str(ctx.label), split=str(ctx.split),
                             demand=np.asarray(tensor.demand[ctx.day], dtype=np.float32), obs=rec["obs"],
                             actions=actions, sr=realized_sr(tensor, scenario, ctx.day, actions, device=device)))
    return plays, result


def realized_sr(tensor, scenario, day: int, actions: np.ndarray, *, device: str = "cpu") -> np.ndarray:
    """(T,) SR_0..SR_{T-1} of tensor day ``day`` played with ``actions`` (T-1, K, 3) in the environment."""
    core = core_from_tensor(tensor, scenario, [day], device=device)
    core.reset([0])
    sr = [float(core.sr0[0])]
    for a in actions:
        sr.append(float(core.step(a[None]).sr[0]))
    return np.asarray(sr, dtype=np.float64)
