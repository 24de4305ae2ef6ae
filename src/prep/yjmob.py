"""YJMob100K dataset 1: raw reader and crop tensor builder.

Raw format: `yjmob100k-dataset1.csv.gz` with header `uid,d,t,x,y`: user id, day 0..74, 30-minute slot
0..47, cell x, y in 1..200 (500 m); x = y = 999 marks a masked record. Every field is an integer: a blank field
or text (`nan`, `NA`, `NULL`, ...) is an error naming the file, line, column and text. Demand = number of
distinct uids per cell and 30-minute slot, divided by 3 into its three 10-minute slots, in the densest 9 x 9
window by TRAINING total. Grid convention: tensor row = y - first_y, col = x - first_x; the dataset does not say
which way y grows, it is taken to grow northward (a mirror image changes no served ratio).
"""
from __future__ import annotations

import logging
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import polars as pl
import pyarrow as pa

from prep.config import YJMobConfig
from prep.days import allowed_empty, numbered_days, recover_week, refuse_empty_days
from prep.grid import densest_window
from prep.rawio import PrepError, describe_sources, first_bad, iter_csv_batches
from prep.tensor import SLOTS_PER_DAY, RawTensor, train_index

log = logging.getLogger(__name__)

COLUMNS = ("uid", "d", "t", "x", "y")
_TYPES = {c: pa.int64() for c in COLUMNS}
_SCHEMA = {"uid": pl.Int64, "d": pl.Int16, "t": pl.Int16, "x": pl.Int16, "y": pl.Int16}


def iter_records(path: Path | str, *, full_size: int = 200, masked_value: int = 999, n_days: int = 75,
                 raw_slots: int = 48, allowed_days: set[int] | None = None, on_out_of_range: str = "error",
                 dropped: dict[str, int] | None = None) -> Iterator[pl.DataFrame]:
    """Streams validated record batches; masked rows are dropped and counted.

    Args:
        path: the csv or csv.gz file.
        full_size: x, y must lie in 1..full_size unless masked.
        masked_value: x = y = masked_value marks a masked record.
        n_days, raw_slots: d must lie in 0..n_days-1 and t in 0..raw_slots-1.
        allowed_days: the configured segments' days (None: all).
        on_out_of_range: "error" or "drop" for cells outside the grid and days outside every segment.
        dropped: counts of dropped rows by reason are added to it.
    Yields:
        DataFrames (uid, d, t, x, y) with compact integer types.
    """
    path = Path(path)
    counts = dropped if dropped is not None else {}
    allowed = None if allowed_days is None else pl.Series(sorted(allowed_days), dtype=pl.Int64)
    for line0, df in iter_csv_batches(path, names=COLUMNS, types=_TYPES, has_header=True):
        for col in COLUMNS:
            i = first_bad(df[col].is_null())
            if i is not None:
                raise PrepError(f"{path}, line {line0 + i}, column {col!r}: expected an integer, found a blank field")
        for col, lo, hi in (("uid", 0, None), ("d", 0, n_days - 1), ("t", 0, raw_slots - 1)):
            bad = (df[col] < lo) | ((df[col] > hi) if hi is not None else False)
            i = first_bad(bad)
            if i is not None:
                want = f"an integer in {lo}..{hi}" if hi is not None else f"an integer >= {lo}"
                raise PrepError(f"{path}, line {line0 + i}, column {col!r}: expected {want}, found {df[col][i]}")
        masked = (df["x"] == masked_value) & (df["y"] == masked_value)
        counts["masked_999"] = counts.get("masked_999", 0) + int(masked.sum())
        df = df.filter(~masked)
        checks = [("cell_outside_grid", lambda f: ~(f["x"].is_between(1, full_size) & f["y"].is_between(1, full_size)),
                   f"expected x, y in 1..{full_size} (or both {masked_value} = masked)")]
        if allowed is not None:
            checks.append(("outside_segments", lambda f: ~f["d"].is_in(allowed.implode()),
                           "expected a day inside a configured segment (datasets.yjmob.split)"))
        for reason, test, expected in checks:
            bad = test(df)  # evaluated on the rows left by the previous check
            i = first_bad(bad)
            if i is None:
                continue
            if on_out_of_range == "error":
                row = df.row(i, named=True)
                raise PrepError(f"{path}, line {_line_of(path, line0, masked, i)}: {expected}, found "
                                f"x={row['x']}, y={row['y']}, d={row['d']}")
            counts[reason] = counts.get(reason, 0) + int(bad.sum())
            df = df.filter(~bad)
        yield df.cast(_SCHEMA)  # type: ignore[arg-type]


def _line_of(path: Path, line0: int, masked: pl.Series, i: int) -> int:
    """Line number of the i-th unmasked row of a batch that starts at line0."""
    keep = np.flatnonzero(~masked.to_numpy())
    return line0 + int(keep[i])


def read_raw(path: Path | str, *, window: tuple[int, int, int, int] | None = None, **kwargs) -> pl.DataFrame:
    """Reads the records of one file (masked rows dropped with a count), optionally only inside a window.

    Args:
        path: yjmob100k-dataset1.csv(.gz).
        window: (first_x, first_y, cols, rows) to keep only records inside it; None keeps all (use a window
            for the full 111.5M-row file: without one the result holds every record).
        **kwargs: passed to `iter_records`.
    Returns:
        DataFrame (uid, d, t, x, y).
    """
    parts = []
    for df in iter_records(path, **kwargs):
        if window is not None:
            x0, y0, w, h = window
            df = df.filter(pl.col("x").is_between(x0, x0 + w - 1) & pl.col("y").is_between(y0, y0 + h - 1))
        parts.append(df)
    return pl.concat(parts) if parts else pl.DataFrame(schema=_SCHEMA)


def distinct_counts(records: pl.DataFrame) -> pl.DataFrame:
    """Distinct uids per (d, t, x, y): DataFrame (d, t, x, y, users)."""
    return records.group_by("d", "t", "x", "y").agg(pl.col("uid").n_unique().alias("users"))


def deaggregate(counts30: np.ndarray, factor: int) -> np.ndarray:
    """Uniform de-aggregation of (..., T30, R, C) counts into (..., T30*factor, R, C), each part count/factor."""
    return np.repeat(counts30 / factor, factor, axis=-3)


def build(cfg: YJMobConfig, paths: list[Path]) -> RawTensor:
    """Builds the YJMob crop tensor (distinct users per 10-min slot) in two streaming passes.

    Pass 1 counts training records per cell over the full grid and picks the densest window; pass 2 keeps the
    window's records only, removes duplicate (uid, d, t, x, y) rows and counts distinct users.
    """
    if len(paths) != 1:
        raise PrepError(f"yjmob: expected exactly one raw file (yjmob100k-dataset1.csv.gz), found {len(paths)}: "
                        f"{[str(p) for p in paths]}")
    path = paths[0]
    days = numbered_days(cfg.split, dataset="yjmob", n_days=cfg.n_days)
    day_numbers = np.array([d.key for d in days])
    train_d = set(int(d.key) for d in days if d.split == "train")
    if SLOTS_PER_DAY % cfg.raw_slots_per_day:
        raise PrepError(f"config key datasets.yjmob.raw_slots_per_day: expected a divisor of {SLOTS_PER_DAY}, "
                        f"found {cfg.raw_slots_per_day}")
    kw = dict(full_size=cfg.full_size, masked_value=cfg.masked_value, n_days=cfg.n_days,
              raw_slots=cfg.raw_slots_per_day, allowed_days=set(day_numbers.tolist()),
              on_out_of_range=cfg.on_out_of_range)
    # Pass 1: training records per cell, records per day.
    n = cfg.full_size
    cell_train = np.zeros(n * n, dtype=np.int64)
    per_day = np.zeros(cfg.n_days, dtype=np.int64)
    dropped: dict[str, int] = {}
    for df in iter_records(path, dropped=dropped, **kw):
        d = df["d"].to_numpy()
        per_day += np.bincount(d, minlength=cfg.n_days)
        tr = np.isin(d, list(train_d))
        flat = (df["y"].to_numpy()[tr].astype(np.int64) - 1) * n + df["x"].to_numpy()[tr] - 1
        cell_train += np.bincount(flat, minlength=n * n)
    empty = refuse_empty_days("yjmob", days, [per_day[d.key] > 0 for d in days], allowed_empty(cfg), [path],
                              what="record", expected="records (uid,d,t,x,y) on every configured day")
    r0, c0, total = densest_window(cell_train.reshape(n, n), cfg.crop.rows, cfg.crop.cols)
    if total == 0:
        raise PrepError(f"{path}: the densest {cfg.crop.rows}x{cfg.crop.cols} window holds no training record")
    y0, x0 = r0 + 1, c0 + 1
    log.info("yjmob: densest window x %d..%d, y %d..%d with %d training records", x0, x0 + cfg.crop.cols - 1,
             y0, y0 + cfg.crop.rows - 1, total)
    # Pass 2: the window's records, distinct users per cell and 30-min slot.
    rec = read_raw(path, window=(x0, y0, cfg.crop.cols, cfg.crop.rows), dropped={}, **kw)
    uniq = rec.unique()
    dropped["duplicate_records"] = rec.height - uniq.height
    cnt = distinct_counts(uniq)
    pos = {int(dn): i for i, dn in enumerate(day_numbers)}
    counts30 = np.zeros((len(days), cfg.raw_slots_per_day, cfg.crop.rows, cfg.crop.cols))
    di = np.array([pos[int(v)] for v in cnt["d"].to_numpy()], dtype=np.int64)
    counts30[di, cnt["t"].to_numpy(), cnt["y"].to_numpy() - y0, cnt["x"].to_numpy() - x0] = cnt["users"].to_numpy()
    values = deaggregate(counts30, SLOTS_PER_DAY // cfg.raw_slots_per_day)
    tr_idx = train_index(days)
    week = recover_week(day_numbers[tr_idx], values[tr_idx].sum(axis=(1, 2, 3)), cfg.week)
    phase = [int(d % week.lag) for d in day_numbers]
    log.info("yjmob: week lag %d, pseudo-weekend phases %s", week.lag, week.pseudo_weekend_phases)
    return RawTensor(
        dataset="yjmob", days=days, values=values, weekday=phase,
        weekend=[p in week.pseudo_weekend_phases for p in phase],
        grid={"rows": cfg.crop.rows, "cols": cfg.crop.cols, "cell_m": cfg.cell_m, "first_x": x0, "first_y": y0,
              "full_size": cfg.full_size,
              "convention": "tensor row r = y - first_y (y taken to grow northward), col c = x - first_x"},
        crop={"rule": "densest_train", "first_x": x0, "first_y": y0, "rows": cfg.crop.rows, "cols": cfg.crop.cols,
              "train_records": int(total)},
        dropped=dropped, sources=describe_sources([path]), empty_days=empty,
        week={"lag": week.lag, "pseudo_weekend_phases": week.pseudo_weekend_phases,
              "acf": {str(k): v for k, v in week.acf.items()}, "phase_means": week.phase_means,
              "phase": "d mod lag", "from": "training daily totals of the crop"})
