"""Reuse of another seed's evaluation by a method whose result the seed does not change
(``evaluation.reuse_seed_independent``; docs/PROTOCOL.md §6)."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import polars as pl

from dswm.methods.base import Controller
from dswm.protocol.evaluation import EvalResult, eval_days, read_method_record, read_model_record, result_hashes
from dswm.sim.core import grid_of
from dswm.sim.scenario import Scenario


def reuse_evaluation(source: Mapping[str, str | Path], *, tensor, controller: Controller, scenario: Scenario,
                     seed: int, limits: Mapping[str, int | None], profile: str,
                     method_record: Mapping[str, Any]) -> tuple[EvalResult, dict]:
    """Another seed's evaluation of a method whose result the seed does not change, as this seed's.

    Every per-day value of such a method is the same at every seed (``controller.deterministic``; the environment
    draws nothing from the seed), so the evaluation of the dataset's first seed stands for the others
    (``evaluation.reuse_seed_independent``): its days with ``seed`` in the seed column and the same trajectories.
    Before anything is reused, the source must be what this job would compute: its content record must match its
    files, and its method, dataset, profile, method record and observation-spec, eval-days and scenario hashes must be
    this job's.

    Args:
        source: {"days", "trajectory", "record"}: the source evaluation's days.parquet, trajectory.npz and
            content record (:data:`dswm.protocol.evaluation.EVAL_RECORD_FILE`).
        tensor, controller, scenario, limits, profile: as :func:`dswm.protocol.evaluation.evaluate` (the controller
            is not run).
        seed: this job's seed.
        method_record: this job's method record (``dswm.pipeline.setup.method_record``).

    Returns:
        (the evaluation at ``seed``, the source's model record).

    Raises:
        ValueError: the controller's class does not say the seed leaves its result unchanged, or the source is not
            this job's evaluation at another seed (the message names the file and what differs); nothing is written.
    """
    from prep.rawio import sha256_file

    days_path, traj_path = Path(source["days"]), Path(source["trajectory"])
    if not controller.deterministic:
        raise ValueError(f"{controller.name}: its class ({type(controller).__name__}) does not say the seed leaves "
                         f"its result unchanged (deterministic); it cannot reuse {days_path}")
    record = json.loads(Path(source["record"]).read_text())
    for name, path in (("days.parquet", days_path), ("trajectory.npz", traj_path)):
        want = record.get("files", {}).get(name, {}).get("sha256")
        if want != sha256_file(path):
            raise ValueError(f"{path}: its SHA-256 is not the one {source['record']} records ({want}); the source "
                             f"evaluation changed since it was written: re-run its evaluate job")
    days = pl.read_parquet(days_path)
    dataset = tensor.meta["dataset"]
    evaluated = eval_days(tensor, limits)
    want = {"method": controller.name, "dataset": dataset, "profile": profile,
            **result_hashes(dataset, grid_of(tensor), scenario, evaluated, tensor.labels)}
    for column, value in want.items():
        found = sorted(set(map(str, days[column].to_list()))) if column in days.columns else []
        if found != [str(value)]:
            raise ValueError(f"{days_path}: column {column} holds {found}; this job's is {value!r}: the source is not "
                             f"this job's evaluation at another seed")
    found_record = read_method_record(days_path)
    if found_record != json.loads(json.dumps(dict(method_record), sort_keys=True)):
        raise ValueError(f"{days_path}: its method record {found_record} is not this job's {dict(method_record)}: the "
                         f"source was evaluated with other settings")
    with np.load(traj_path, allow_pickle=False) as npz:
        trajectories = {k: npz[k] for k in npz.files}
    days = days.with_columns(pl.lit(seed, dtype=pl.Int32).alias("seed"))
    return EvalResult(days=days, trajectories=trajectories), read_model_record(days_path)
