"""Settings that the paper leaves open, chosen on TRAINING days only (docs/PROTOCOL.md §5).

The training days of one dataset are split in time order: the first ``fit_days`` fit a world model, the later
ones validate. Two choices are made there, and nowhere else:

* the strength of the project's one BCD ``search``: Greedy runs every candidate on the validation days; the
  candidate with the best served ratio whose planning time per day-slot is within the budget wins;
* the planner discount gamma and initial std sigma0 of the planner method (``dswm``, Algorithm 1): its world
  model is fitted on the fit days, then every (gamma, sigma0) pair plans the validation days; the best served
  ratio wins (ties: the first pair in config order).

The result is a report; config.yaml keeps the chosen values (the pipeline never depends on a timing). Test days
are never read: only ``tensor.train_days`` are.
"""
from __future__ import annotations

import dataclasses
import sys
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from dswm.config import to_plain
from dswm.methods.base import Controller
from dswm.methods.search import SearchSettings
from dswm.protocol.evaluation import evaluate
from dswm.sim.core import core_from_tensor
from dswm.sim.scenario import Scenario


def split_training_days(tensor, fit_days: int) -> tuple[list[int], list[int]]:
    """(fit days, validation days): the tensor's training days in time order, the first ``fit_days`` and the rest.

    Raises:
        ValueError: fewer than ``fit_days + 1`` training days.
    """
    train = [int(d) for d in tensor.train_days]
    if len(train) <= fit_days:
        raise ValueError(f"meta.json of {tensor.meta['dataset']}: {len(train)} training day(s), but "
                         f"selection.fit_days = {fit_days} needs at least {fit_days + 1} (the rest validate)")
    return train[:fit_days], train[fit_days:]


def score_days(*, tensor, controller: Controller, scenario: Scenario, days: Sequence[int], seed: int, device: str,
               batch_days: bool, progress_interval_s: float) -> dict[str, Any]:
    """Served ratio of ``controller`` on the given (training) days, through the evaluation's own loop.

    Returns:
        {"sr_mean": mean over days, "sr_per_day": {label: value}, "ms_per_slot": planning time per day-slot}.
    """
    result = evaluate(tensor=tensor, controller=controller, scenario=scenario, seed=seed, limits={},
                      days={"train": list(days)}, profile="selection", device=device, batch_days=batch_days,
                      progress_interval_s=progress_interval_s, trajectory=False)
    d = result.days
    return {"sr_mean": float(d["sr_mean"].mean()),
            "sr_per_day": {lab: round(float(v), 6) for lab, v in zip(d["label"], d["sr_mean"])},
            "ms_per_slot": float(d["plan_ms_per_slot"].mean())}


def select_search(*, make: Callable[[SearchSettings], Controller], candidates: Sequence[SearchSettings],
                  budget_ms: float, **score_kw) -> dict[str, Any]:
    """Greedy with every candidate search on the validation days; the best served ratio within ``budget_ms``.

    Args:
        make: builds the Greedy controller of one search setting.
        candidates: the search settings compared, in config order (ties go to the earlier one).
        budget_ms: the largest planning time per day-slot a chosen candidate may cost.
        **score_kw: :func:`score_days`' arguments but ``controller``.
    """
    rows = []
    for cand in candidates:
        print(f"select: search {to_plain(cand)}", file=sys.stderr)
        rows.append({"search": to_plain(cand), **score_days(controller=make(cand), **score_kw)})
    within = [r for r in rows if r["ms_per_slot"] <= budget_ms]
    best = max(within, key=lambda r: r["sr_mean"]) if within else None
    return {"candidates": rows, "budget_ms": budget_ms, "chosen": None if best is None else best["search"]}


def select_planner(*, controller: Controller, tensor, scenario: Scenario, fit_days: Sequence[int],
                   gammas: Sequence[float], sigma0s: Sequence[float], run_dir: str | Path,
                   **score_kw) -> dict[str, Any]:
    """Fit ``controller``'s world model on ``fit_days``, then plan the validation days with every (gamma, sigma0).

    Args:
        controller: the planner method (a DSWM controller with its resolved settings).
        fit_days: tensor days of the fit (training days only).
        gammas, sigma0s: the candidate values (config order; ties go to the earlier pair).
        run_dir: where the fit writes its checkpoint.
        **score_kw: :func:`score_days`' arguments but ``controller``, ``tensor`` and ``scenario``.
    """
    core = core_from_tensor(tensor, scenario, fit_days, device=score_kw["device"])
    print(f"select: fitting {controller.name}'s world model on {len(fit_days)} training day(s)", file=sys.stderr)
    controller.fit(core, run_dir=run_dir)
    base = controller.options
    rows = []
    for g in gammas:
        for s0 in sigma0s:
            controller.options = dataclasses.replace(base, planner=dataclasses.replace(base.planner, gamma=float(g),
                                                                                        sigma0=float(s0)))
            print(f"select: {controller.name} gamma={g} sigma0={s0}", file=sys.stderr)
            rows.append({"gamma": float(g), "sigma0": float(s0),
                         **score_days(controller=controller, tensor=tensor, scenario=scenario, **score_kw)})
    controller.options = base
    best = max(rows, key=lambda r: r["sr_mean"])
    fit_labels = [tensor.labels[d] for d in fit_days]
    return {"method": controller.name, "fit_days": fit_labels, "candidates": rows,
            "chosen": {"gamma": best["gamma"], "sigma0": best["sigma0"]},
            "spread_sr": float(np.ptp([r["sr_mean"] for r in rows]))}
