"""Demand tensors: training-only normalization, kappa alignment, metadata, atomic writing and loading.

A dataset builder (prep.milan / prep.shanghai / prep.yjmob) produces a `RawTensor` in raw units; `finalize`
divides by the TRAINING p99 and multiplies by kappa; `write` stores the long-form Parquet and meta.json
(docs/ARCHITECTURE.md, "Demand tensor"); `load` gives the dense (days, 144, rows, cols) float32 tensor back.
"""
from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import polars as pl

from prep import stats
from prep.atomic import atomic_group
from prep.config import CommonPrep, DatasetConfig
from prep.days import Day
from prep.rawio import PrepError

SLOTS_PER_DAY = 144
TENSOR_FILE = "demand.parquet"
META_FILE = "meta.json"
_COLUMNS = {"day": pl.Int32, "slot": pl.Int16, "row": pl.Int16, "col": pl.Int16, "demand": pl.Float32}


@dataclass(kw_only=True)
class RawTensor:
    """A dataset's crop in raw units, before normalization.

    values: (D, 144, rows, cols) float64, demand in the dataset's raw unit.
    weekday: per day, 0=Mon..6 (or the recovered week phase for YJMob); weekend: per day flag.
    grid: {rows, cols, cell_m, ...origin info}; crop: how the window was chosen; dropped: counts by reason;
    sources: [{name, bytes, sha256}]; week: recovered week (YJMob) or None; empty_days: labels with no record;
    notes: counts worth knowing that are not drops (kept sessions crossing midnight, files skipped unread).
    """

    dataset: str
    days: list[Day]
    values: np.ndarray
    weekday: list[int]
    weekend: list[bool]
    grid: dict
    crop: dict
    dropped: dict[str, int]
    sources: list[dict]
    week: dict | None = None
    empty_days: list[str] = field(default_factory=list)
    notes: dict[str, int] = field(default_factory=dict)


def train_index(days: list[Day]) -> np.ndarray:
    """Tensor indices of the training days."""
    return np.array([d.index for d in days if d.split == "train"], dtype=np.int64)


def finalize(raw: RawTensor, *, common: CommonPrep, cfg: DatasetConfig, source: str,
             eval_days: dict[str, list[int]], reference_mean: float | None) -> tuple[np.ndarray, dict]:
    """Normalizes by the TRAINING percentile, aligns intensity by kappa and assembles meta.json.

    Args:
        raw: the dataset's crop in raw units.
        common: shared settings (percentile, kappa reference dataset, top-cell fraction).
        cfg: the dataset's config (recorded in meta).
        source: "demo" or "raw".
        eval_days: {"id": [...], "ood": [...]} tensor day indices.
        reference_mean: the reference dataset's training mean of normalized demand (None for the reference).
    Returns:
        (demand (D,144,R,C) float32, meta dict).
    """
    tr = train_index(raw.days)
    p99 = stats.percentile(raw.values, tr, common.norm_percentile)
    if not p99 > 0:
        raise PrepError(f"{raw.dataset}: the {common.norm_percentile}th percentile of the training crop is "
                        f"{p99}; expected > 0 (the crop holds too little training data)")
    p99_all = stats.percentile(raw.values, np.arange(len(raw.days)), common.norm_percentile)
    norm = raw.values / p99
    train_mean = stats.mean_of(norm, tr)
    if raw.dataset == common.kappa_reference:
        kappa, ref = 1.0, train_mean
    else:
        if reference_mean is None or not reference_mean > 0:
            raise PrepError(f"{raw.dataset}: kappa needs the training mean of {common.kappa_reference}, "
                            f"found {reference_mean}")
        kappa, ref = reference_mean / train_mean, reference_mean
    demand = (norm * kappa).astype(np.float32)
    labels = [d.label for d in raw.days]
    seg = {s: [labels[i] for i, d in enumerate(raw.days) if d.split == s] for s in ("train", "test")}
    meta = {
        "dataset": raw.dataset,
        "source": source,
        "grid": raw.grid,
        "slots_per_day": SLOTS_PER_DAY,
        "days": [{"index": d.index, "label": d.label, "split": d.split, "weekday": int(raw.weekday[d.index]),
                  "weekend": bool(raw.weekend[d.index])} for d in raw.days],
        "split": {s: [v[0], v[-1]] for s, v in seg.items()},
        "eval_days": {k: [int(i) for i in v] for k, v in eval_days.items()},
        "p99": p99,
        "p99_all_days": p99_all,
        "kappa": kappa,
        "kappa_reference_mean": ref,
        "train_mean_normalized": train_mean,
        "week": raw.week,
        "zero_cell_rate": stats.zero_cell_rate(demand),
        "top5_share": stats.top_share(demand, common.top_share_frac),
        "crop": raw.crop,
        "sources": raw.sources,
        "dropped": {k: int(v) for k, v in sorted(raw.dropped.items())},
        "empty_days": raw.empty_days,
        "notes": {k: int(v) for k, v in sorted(raw.notes.items())},
        "config": dataclasses.asdict(cfg),
    }
    return demand, meta


def to_long(demand: np.ndarray) -> pl.DataFrame:
    """Long form (day, slot, row, col, demand) of the non-zero entries of a (D,T,R,C) tensor."""
    d, t, r, c = np.nonzero(demand)
    return pl.DataFrame({"day": d.astype(np.int32), "slot": t.astype(np.int16), "row": r.astype(np.int16),
                         "col": c.astype(np.int16), "demand": demand[d, t, r, c].astype(np.float32)})


def write(out_dir: Path | str, demand: np.ndarray, meta: dict) -> None:
    """Writes demand.parquet and meta.json atomically (both or neither)."""
    out_dir = Path(out_dir)
    with atomic_group([out_dir / TENSOR_FILE, out_dir / META_FILE]) as (tmp_tensor, tmp_meta):
        to_long(demand).write_parquet(tmp_tensor, compression="zstd", statistics=True)
        tmp_meta.write_text(json.dumps(meta, indent=2, sort_keys=True) + "\n")


@dataclass(frozen=True, kw_only=True)
class GridSpec:
    """Grid of the tensor (the fields of dswm.sim.core.Grid; ``dswm.sim.core.grid_of`` converts it)."""

    rows: int
    cols: int
    cell_m: float


@dataclass(frozen=True, kw_only=True)
class DemandTensor:
    """A prepared dataset: `demand` (days, 144, rows, cols) float32 = normalized by the training p99 x kappa."""

    demand: np.ndarray
    meta: dict
    grid: GridSpec

    @property
    def train_days(self) -> np.ndarray:
        return np.array([d["index"] for d in self.meta["days"] if d["split"] == "train"], dtype=np.int64)

    @property
    def test_days(self) -> np.ndarray:
        return np.array([d["index"] for d in self.meta["days"] if d["split"] == "test"], dtype=np.int64)

    @property
    def labels(self) -> list[str]:
        return [d["label"] for d in self.meta["days"]]

    def eval_days(self, split: str) -> np.ndarray:
        """Tensor day indices of the evaluation days of `split` ("id" or "ood")."""
        if split not in ("id", "ood"):
            raise ValueError(f"eval split must be 'id' or 'ood', found {split!r}")
        return np.asarray(self.meta["eval_days"][split], dtype=np.int64)


# The meta.json keys readers rely on, with the form each must have.
_META_KEYS = {"dataset": (str, "a dataset name"), "source": (str, '"demo" or "raw"'),
              "slots_per_day": (int, "an integer"), "grid": (dict, "{rows, cols, cell_m}"),
              "days": (list, "a list of {index, label, split, ...}"), "kappa": ((int, float), "a number"),
              "train_mean_normalized": ((int, float), "a number"), "eval_days": (dict, "{id: [...], ood: [...]}")}
_DAY_KEYS = ("index", "label", "split")


def read_meta(path: Path | str, *, keys: tuple[str, ...] = tuple(_META_KEYS)) -> dict:
    """Reads and checks a meta.json written by `write`.

    Args:
        path: the meta.json; keys: the top-level keys the caller reads (default: every key `load` needs).
    Raises:
        PrepError: the file is missing, not JSON, or lacks a key readers use (the message names the key, the
            form expected and what was found).
    """
    path = Path(path)
    if not path.is_file():
        raise PrepError(f"{path}: no such file (run the `prepare` rule)")
    try:
        meta = json.loads(path.read_text())
    except ValueError as exc:
        raise PrepError(f"{path}: not valid JSON ({exc}); rerun the `prepare` rule") from exc
    if not isinstance(meta, dict):
        raise PrepError(f"{path}: expected a JSON object, found {type(meta).__name__}")
    for key in keys:
        kind, form = _META_KEYS[key]
        if key not in meta:
            raise PrepError(f"{path}: missing key {key!r} (expected {form}); rerun the `prepare` rule")
        if not isinstance(meta[key], kind) or isinstance(meta[key], bool):
            raise PrepError(f"{path}: key {key!r} expected {form}, found {meta[key]!r}")
    for key in ("rows", "cols", "cell_m") if "grid" in keys else ():
        if not isinstance(meta["grid"].get(key), (int, float)):
            raise PrepError(f"{path}: key 'grid.{key}' expected a number, found {meta['grid'].get(key)!r}")
    for i, day in enumerate(meta["days"] if "days" in keys else ()):
        missing = [k for k in _DAY_KEYS if not isinstance(day, dict) or k not in day]
        if missing:
            raise PrepError(f"{path}: days[{i}] lacks {missing} (expected {{index, label, split, ...}}), "
                            f"found {day!r}")
    return meta


def load(dataset_dir: Path | str) -> DemandTensor:
    """Loads a prepared dataset.

    Args:
        dataset_dir: directory holding demand.parquet and meta.json (results/data/{dataset}).
    Returns:
        DemandTensor with the dense tensor (absent long-form rows are zero).
    Raises:
        PrepError: a file is missing or does not match the contract.
    """
    dataset_dir = Path(dataset_dir)
    meta_path, tensor_path = dataset_dir / META_FILE, dataset_dir / TENSOR_FILE
    meta = read_meta(meta_path)
    if not tensor_path.is_file():
        raise PrepError(f"{tensor_path}: no such file (run the `prepare` rule)")
    grid = GridSpec(rows=int(meta["grid"]["rows"]), cols=int(meta["grid"]["cols"]),
                    cell_m=float(meta["grid"]["cell_m"]))
    n_days, n_slots = len(meta["days"]), int(meta["slots_per_day"])
    df = pl.read_parquet(tensor_path)
    schema = dict(df.schema)
    if schema != _COLUMNS:
        raise PrepError(f"{tensor_path}: expected columns {_COLUMNS}, found {schema}")
    demand = np.zeros((n_days, n_slots, grid.rows, grid.cols), dtype=np.float32)
    if df.height:
        idx = [df[c].to_numpy().astype(np.int64) for c in ("day", "slot", "row", "col")]
        for arr, hi, name in zip(idx, demand.shape, ("day", "slot", "row", "col")):
            if arr.min() < 0 or arr.max() >= hi:
                raise PrepError(f"{tensor_path}: column {name!r} expected in 0..{hi - 1}, "
                                f"found {arr.min()}..{arr.max()}")
        demand[idx[0], idx[1], idx[2], idx[3]] = df["demand"].to_numpy()
    return DemandTensor(demand=demand, meta=meta, grid=grid)
