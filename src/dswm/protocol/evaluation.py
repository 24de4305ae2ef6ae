"""Per-day evaluation of one controller on the fixed ID and OOD days of a dataset (docs/PROTOCOL.md §3, §6).

Every method runs the same days through the same ``FleetCore`` from the same initial state (demand-weighted
K-means of the mean TRAINING map; batteries drawn from (dataset, day) alone). A day's score is the mean of
its 144 served-ratio values (SR_0 of the initial deployment, then one per decision). The evaluated days of a
job are stepped as one batch when the controller is batched. A per-slot bound (``Controller.places``, the ceiling)
is asked for a placement of the whole fleet each slot instead of an action, served by ``FleetCore.place`` with the
same physics and every UAV available; it flies no fleet, so its energy columns are null. The per-day table this
module returns is the source of truth for the tables and the leakage audit (docs/ARCHITECTURE.md, "Results");
:func:`write_days` stores it with two records in the file's metadata: the model the evaluation loaded
(:data:`MODEL_RECORD_KEY`) and the method's resolved settings, its BCD search included (:data:`METHOD_RECORD_KEY`).
"""
from __future__ import annotations

import dataclasses
import json
import math
import numbers
import re
import sys
import time
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import polars as pl
import torch
from tqdm import tqdm

from prep.atomic import atomic_path
from dswm.config import stable_hash
from dswm.sim.scenario import Scenario
from dswm.methods.base import Controller, DayContext
from dswm.sim.core import Grid, core_from_tensor, obs_spec_hash

DAY_COLUMNS = ["day", "label", "split", "sr_mean", "energy_kj_per_slot", "energy_efficiency", "jain",
               "plan_ms_per_slot", "obs_spec_hash", "eval_days_hash", "scenario_hash", "seed", "method",
               "dataset", "profile", "data_source"]

STAT_PREFIX = "stat_"
"""Prefix of the extra columns of days.parquet that a controller reports per day (``Controller.day_stats``); they
follow DAY_COLUMNS, sorted, as Float64, null for a day whose controller did not report that key."""

MODEL_RECORD_KEY = "dswm.evaluated_model"
"""days.parquet metadata key of the model record: JSON {method, train_source, model, model_sha256,
train_manifest}; the last four are null for a method that does not learn."""
MODEL_RECORD_FIELDS = ("method", "train_source", "model", "model_sha256", "train_manifest")

METHOD_RECORD_KEY = "dswm.method_settings"
"""days.parquet metadata key of the method record: JSON {method, class, options, search}: the evaluated method,
its controller class ("package.module:ClassName"), its resolved typed settings in plain form
(``dswm.config.to_plain`` of ``MethodSettings.options``) and the block-coordinate-descent search it ran
(``to_plain`` of ``Controller.search_settings()``; null for a method that runs none)."""
METHOD_RECORD_FIELDS = ("method", "class", "options", "search")


@dataclasses.dataclass(frozen=True, kw_only=True)
class EvalResult:
    """Outcome of one (dataset, method, seed) evaluation."""

    days: pl.DataFrame
    """One row per evaluated day, columns DAY_COLUMNS, then any ``stat_`` columns of the controller (STAT_PREFIX)."""
    trajectories: dict[str, np.ndarray]
    """Fleet positions per slot of the first ID and the first OOD day: ``{split}_pos`` (T, K, 2) metres,
    ``{split}_status`` (T, K), ``{split}_day`` (), ``{split}_label`` ()."""


def eval_days(tensor, limits: Mapping[str, int | None]) -> dict[str, list[int]]:
    """The evaluated tensor day indices per split: the configured days, cut to the profile's limit.

    Args:
        tensor: a prep.tensor.DemandTensor.
        limits: {"id": N or None, "ood": N or None}.
    """
    out = {}
    for split in ("id", "ood"):
        days = [int(d) for d in tensor.eval_days(split)]
        if not days:
            raise ValueError(f"meta.json of {tensor.meta['dataset']}: eval_days.{split} is empty; expected at least "
                             f"one test day")
        out[split] = days[: limits[split]] if limits[split] is not None else days
    return out


def eval_days_hash(dataset: str, days: Mapping[str, list[int]], labels: list[str]) -> str:
    """Hash of the evaluated days (indices and labels per split); the audit compares it across methods."""
    return stable_hash({"dataset": dataset, **{s: [[d, labels[d]] for d in days[s]] for s in days}})


def result_hashes(dataset: str, grid: Grid, scenario: Scenario, days: Mapping[str, list[int]],
                  labels: list[str]) -> dict[str, str]:
    """The three hashes every days.parquet carries, {"obs_spec_hash", "eval_days_hash", "scenario_hash"}: of the
    observation spec on ``grid``, of the evaluated ``days`` and of the scenario. The
    evaluation writes them, a reused evaluation and the audit (``audits.hashes``) check them against these."""
    return {"obs_spec_hash": obs_spec_hash(grid, scenario), "eval_days_hash": eval_days_hash(dataset, days, labels),
            "scenario_hash": scenario.hash()}


def check_demand_in_every_slot(tensor, days: Mapping[str, list[int]]) -> None:
    """Refuse a day to evaluate that holds a slot with zero total demand in the crop.

    The served ratio of such a slot is undefined (the physics reports 1 there, ``dswm.sim.physics.service``),
    so a day with one would score a free 1.0 for that slot. A cell counts as demand as in the physics (above
    ``DEMAND_EPS``).

    Args:
        tensor: a prep.tensor.DemandTensor; days: {split: tensor day indices} about to be evaluated.
    Raises:
        ValueError: naming the dataset, the day's label and split, and the slot(s).
    """
    from dswm.sim.physics import DEMAND_EPS

    for split, idx in days.items():
        for day in idx:
            x = tensor.demand[int(day)]
            total = np.where(x > DEMAND_EPS, x, 0.0).sum(axis=(1, 2), dtype=np.float64)
            zero = np.flatnonzero(total <= 0.0).tolist()
            if zero:
                raise ValueError(f"{tensor.meta['dataset']}: evaluation day {tensor.labels[int(day)]} ({split}) has "
                                 f"zero total demand in the crop in slot(s) {zero}; expected demand in every slot "
                                 f"(the served ratio of an empty slot is undefined, never scored as 1.0)")


def evaluate(*, tensor, controller: Controller, scenario: Scenario, seed: int, limits: Mapping[str, int | None],
             profile: str, device: str, batch_days: bool, progress_interval_s: float,
             trajectory: bool = True, days: Mapping[str, list[int]] | None = None) -> EvalResult:
    """Run ``controller`` on the evaluation days of ``tensor``.

    Args:
        tensor: a prep.tensor.DemandTensor (demand (D, T, R, C), meta, grid).
        controller: the method, fitted already if it learns.
        scenario: constants.
        seed: the job's seed (torch and numpy are seeded with it).
        limits: days per split kept by the profile.
        profile: profile name, recorded in every row.
        device: torch device of the environment.
        batch_days: step every evaluated day as one batch when the controller is batched.
        progress_interval_s: tqdm refresh interval.
        trajectory: keep fleet positions per slot of the first day of each split.
        days: {split: tensor days} run instead of the configured evaluation days (the selection on TRAINING
            days, ``dswm.protocol.selection``, passes {"train": [...]}); ``limits`` is then not used.

    Returns:
        EvalResult.

    Raises:
        ValueError: a day to evaluate has a slot with zero total demand (:func:`check_demand_in_every_slot`),
            before any controller runs.
    """
    torch.manual_seed(seed)
    np.random.seed(seed)
    dataset = tensor.meta["dataset"]
    days = eval_days(tensor, limits) if days is None else {s: [int(d) for d in v] for s, v in days.items()}
    check_demand_in_every_slot(tensor, days)
    labels = tensor.labels
    order = [(s, d) for s in days for d in days[s]]  # core index i <-> order[i]
    core = core_from_tensor(tensor, scenario, [d for _, d in order], device=device)
    grid, init_pos = core.grid, core.init_pos.cpu().numpy()
    geometry, cells = grid.geometry(), grid.cells(device=device)

    def context(i: int) -> DayContext:
        split, day = order[i]
        return DayContext(dataset=dataset, day=day, label=labels[day], split=split, grid=grid, scenario=scenario,
                          geometry=geometry, cells=cells, init_pos=init_pos, device=device,
                          demand=tensor.demand[day] if controller.clairvoyant else None)

    n, steps = len(order), scenario.slots_per_day - 1
    batches = [list(range(n))] if (batch_days and controller.batched) else [[i] for i in range(n)]
    keep = {days[s][0]: s for s in days if days[s]} if trajectory else {}
    rows, traj = [], {}
    bar = tqdm(total=n * steps, desc=f"{dataset}/{controller.name}/seed{seed}", unit="day-slot",
               file=sys.stderr, mininterval=progress_interval_s, dynamic_ncols=False, ascii=True)
    for batch in batches:
        obs = core.reset(batch)
        if controller.batched:
            controller.reset_batch([context(i) for i in batch])
        else:
            controller.reset(context(batch[0]))
        sr, jain, energy = [core.sr0], [core.jain0], []
        pos, status = [core.state.pos.cpu().numpy()], [core.state.status.cpu().numpy()]
        plan_s = 0.0
        for _ in range(steps):
            t0 = time.perf_counter()
            if controller.places:  # a per-slot bound: its placement, served with every UAV and no motion limit
                placement = controller.place_batch(obs)
                plan_s += time.perf_counter() - t0
                out = core.place(*placement)
            else:
                action = controller.act_batch(obs) if controller.batched else controller.act(
                    {k: v[0] for k, v in obs.items()})[None]
                plan_s += time.perf_counter() - t0
                out = core.step(action)
            obs = out.obs
            sr.append(out.sr)
            jain.append(out.jain)
            energy.append(out.energy_j)
            pos.append(core.state.pos.cpu().numpy())
            status.append(core.state.status.cpu().numpy())
            bar.update(len(batch))
        sr_a, jain_a, energy_a = np.stack(sr, 1), np.stack(jain, 1), np.stack(energy, 1)  # (B, T) / (B, T-1)
        pos_a, status_a = np.stack(pos, 1), np.stack(status, 1)  # (B, T, K, 2) / (B, T, K)
        stats = day_stat_columns(controller, len(batch))
        for b, i in enumerate(batch):
            split, day = order[i]
            e_kj = None if controller.places else float(energy_a[b].mean()) / 1000.0  # a bound flies no fleet
            rows.append({"day": day, "label": labels[day], "split": split, "sr_mean": float(sr_a[b].mean()),
                         "energy_kj_per_slot": e_kj,
                         "energy_efficiency": None if e_kj is None else float(sr_a[b].mean()) / (e_kj / 1000.0),
                         "jain": float(jain_a[b].mean()), "plan_ms_per_slot": 1000.0 * plan_s / (len(batch) * steps),
                         **stats[b]})
            if keep.get(day) == split:
                traj.update({f"{split}_pos": pos_a[b].astype(np.float32), f"{split}_status": status_a[b],
                             f"{split}_day": np.int64(day), f"{split}_label": np.str_(labels[day])})
    bar.close()
    const = {**result_hashes(dataset, grid, scenario, days, labels), "seed": seed, "method": controller.name,
             "dataset": dataset, "profile": profile, "data_source": str(tensor.meta["source"])}
    stat_cols = sorted({c for r in rows for c in r if c.startswith(STAT_PREFIX)})
    df = pl.DataFrame([{**dict.fromkeys(stat_cols), **r, **const} for r in rows]).select(DAY_COLUMNS + stat_cols)
    df = df.with_columns(pl.col("day").cast(pl.Int32), pl.col("seed").cast(pl.Int32),
                         *[pl.col(c).cast(pl.Float64) for c in ("energy_kj_per_slot", "energy_efficiency", *stat_cols)])
    return EvalResult(days=df, trajectories=traj)


def day_stat_columns(controller: Controller, n_days: int) -> list[dict[str, float]]:
    """The controller's ``day_stats()`` for the ``n_days`` days of its last reset, keys prefixed with STAT_PREFIX.

    Raises:
        ValueError: naming the method, when it reports another number of days than ``n_days``, a key that is not a
            lower-case name, or a value that is not a finite number.
    """
    stats = controller.day_stats()
    if not stats:
        return [{} for _ in range(n_days)]
    if len(stats) != n_days:
        raise ValueError(f"method {controller.name!r}: day_stats() reported {len(stats)} day(s); expected one mapping "
                         f"per day of the last reset ({n_days})")
    out = []
    for day in stats:
        row = {}
        for key, value in day.items():
            if not (isinstance(key, str) and re.fullmatch(r"[a-z][a-z0-9_]*", key)):
                raise ValueError(f"method {controller.name!r}: day_stats() key {key!r}; expected a lower-case name "
                                 f"of letters, digits and underscores")
            if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(value):
                raise ValueError(f"method {controller.name!r}: day_stats() value {key}={value!r}; expected a finite "
                                 f"number")
            row[STAT_PREFIX + key] = float(value)
        out.append(row)
    return out


def stat_columns(days: pl.DataFrame) -> list[str]:
    """The controller's per-day ``stat_`` columns of a days table (STAT_PREFIX), in column order."""
    return [c for c in days.columns if c.startswith(STAT_PREFIX)]


def split_summary(days: pl.DataFrame) -> dict[str, float]:
    """Per-split means of the day metrics and of the controller's ``stat_`` columns, named ``{split}/{metric}``
    (MLflow metric names); a column with no value in a split is left out."""
    out = {}
    for split in ("id", "ood"):
        part = days.filter(pl.col("split") == split)
        for col in ("sr_mean", "energy_kj_per_slot", "energy_efficiency", "jain", "plan_ms_per_slot",
                    *stat_columns(days)):
            mean = part[col].mean()
            if mean is not None:
                out[f"{split}/{col}"] = float(mean)
    return out


def _check_record(path: str | Path, what: str, record: Mapping[str, Any], fields: tuple[str, ...]) -> None:
    """Raise ValueError naming ``path`` when ``record`` is not a mapping holding every one of ``fields``."""
    if not isinstance(record, Mapping):
        raise ValueError(f"{path}: {what} record is {type(record).__name__}; expected a mapping with the fields "
                         f"{list(fields)}")
    missing = [k for k in fields if k not in record]
    if missing:
        raise ValueError(f"{path}: {what} record lacks {missing}; expected the fields {list(fields)}")


def write_days(days: pl.DataFrame, path: str | Path, model_record: Mapping[str, Any],
               method_record: Mapping[str, Any]) -> None:
    """Write days.parquet atomically, with two JSON records in its metadata: ``model_record`` under
    :data:`MODEL_RECORD_KEY` and ``method_record`` under :data:`METHOD_RECORD_KEY`.

    Args:
        days: the per-day table (``EvalResult.days``).
        path: the result file.
        model_record: {field: value} for every field of :data:`MODEL_RECORD_FIELDS`.
        method_record: {field: value} for every field of :data:`METHOD_RECORD_FIELDS`
            (``dswm.pipeline.setup.method_record``): ``method`` and ``class`` strings, ``search`` a mapping or None,
            everything JSON-serializable.

    Raises:
        ValueError: a record lacks a field or holds a value of the wrong kind; nothing is written.
    """
    _check_record(path, "model", model_record, MODEL_RECORD_FIELDS)
    _check_record(path, "method", method_record, METHOD_RECORD_FIELDS)
    if not isinstance(method_record["method"], str) or not method_record["method"]:
        raise ValueError(f"{path}: method record: method = {method_record['method']!r}; expected the method name")
    cls = method_record["class"]
    if not isinstance(cls, str) or ":" not in cls:
        raise ValueError(f"{path}: method record: class = {cls!r}; expected \"package.module:ClassName\"")
    if method_record["search"] is not None and not isinstance(method_record["search"], Mapping):
        raise ValueError(f"{path}: method record: search = {method_record['search']!r}; expected the plain "
                         f"search settings (a mapping) or None")
    metadata = {}
    for key, record in ((MODEL_RECORD_KEY, model_record), (METHOD_RECORD_KEY, method_record)):
        try:
            metadata[key] = json.dumps(dict(record), sort_keys=True, allow_nan=False)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{path}: {key} record is not plain JSON ({exc}); expected the plain form "
                             f"(dswm.config.to_plain) of its values") from exc
    with atomic_path(path) as tmp:
        days.write_parquet(tmp, metadata=metadata)


def _read_record(path: str | Path, key: str) -> dict | None:
    """The JSON object stored under metadata ``key`` of a parquet file, or None when the key is absent."""
    raw = pl.read_parquet_metadata(path).get(key)
    if raw is None:
        return None
    try:
        record = json.loads(raw)
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: metadata {key} is not JSON ({exc})") from exc
    if not isinstance(record, dict):
        raise ValueError(f"{path}: metadata {key} = {raw!r}; expected a JSON object")
    return record


def read_model_record(path: str | Path) -> dict | None:
    """The model record :func:`write_days` stored in days.parquet, or None for a file written without one.

    Raises:
        ValueError: the record is not a JSON object.
    """
    return _read_record(path, MODEL_RECORD_KEY)


def read_method_record(path: str | Path) -> dict | None:
    """The method record :func:`write_days` stored in days.parquet ({method, class, options, search}), or None
    for a file written without one.

    Raises:
        ValueError: the record is not a JSON object.
    """
    return _read_record(path, METHOD_RECORD_KEY)


EVAL_RECORD_FILE = "eval_manifest.json"
"""The content record an evaluate job writes beside its result files, last: JSON {"files": {name: {"sha256",
"bytes"}}} of every file of :data:`EVAL_OUTPUTS` (:func:`write_eval_record`)."""
EVAL_OUTPUTS = ("days.parquet", "trajectory.npz")
"""The result files of an evaluate job (file names in its run directory), the ones its content record covers."""


def write_eval_record(path: str | Path, outputs: Mapping[str, str | Path]) -> dict:
    """Write the content record of an evaluation's result files atomically; call it once they are complete.

    Args:
        path: the record (``<run directory>/`` :data:`EVAL_RECORD_FILE`).
        outputs: {name of :data:`EVAL_OUTPUTS`: the file written}, every one of them.

    Returns:
        The record written: {"files": {name: {"sha256": hex SHA-256, "bytes": size}}}.

    Raises:
        ValueError: ``outputs`` does not name exactly the files of :data:`EVAL_OUTPUTS`; nothing is written.
    """
    from prep.atomic import write_json
    from prep.rawio import sha256_file

    if sorted(outputs) != sorted(EVAL_OUTPUTS):
        raise ValueError(f"{path}: a content record covers {list(EVAL_OUTPUTS)}, got {sorted(outputs)}")
    record = {"files": {name: {"sha256": sha256_file(Path(outputs[name])), "bytes": Path(outputs[name]).stat().st_size}
                        for name in EVAL_OUTPUTS}}
    write_json(path, record)
    return record

