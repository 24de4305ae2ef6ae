"""Milan CDR (Telecom Italia, "SMS, Call, Internet - MI"): raw reader and crop tensor builder.

Raw format: daily `sms-call-internet-mi-YYYY-MM-DD.txt` (or .txt.gz), tab-separated, no header, 8 fields:
square id, time interval (ms since the epoch, UTC, start of a 10-minute slot), country code, sms-in, sms-out,
call-in, call-out, internet. A blank field means no activity; any other text that is not a finite number
(``nan``, ``NA``, ``NULL``, ``inf``, ...) is an error naming the file, line, column and text. One square and slot
has one line per country code. Demand = internet summed over country codes per square and slot; days and slots
are local time. One file per date; exact duplicate lines are dropped and counted; every configured day must have
a line in the crop unless ``allow_empty_days`` lists it.
"""
from __future__ import annotations

import datetime as dt
import logging
import re
from collections.abc import Sequence
from pathlib import Path
from zoneinfo import ZoneInfo

import numpy as np
import polars as pl
import pyarrow as pa
from tqdm import tqdm

from prep.config import MilanConfig
from prep.days import allowed_empty, calendar_days, refuse_empty_days
from prep.rawio import PrepError, describe_sources, first_bad, iter_csv_batches
from prep.tensor import SLOTS_PER_DAY, RawTensor

log = logging.getLogger(__name__)

COLUMNS = ("square_id", "time_interval_ms", "country_code", "sms_in", "sms_out", "call_in", "call_out",
           "internet")
# Every field is read and checked as a number (so that exact duplicate lines can be told apart, and no field holds
# text such as nan or NULL); only internet is summed.
_READ_TYPES = {c: pa.int64() if c in ("square_id", "time_interval_ms", "country_code") else pa.float64()
               for c in COLUMNS}
_DATE_IN_NAME = re.compile(r"(\d{4}-\d{2}-\d{2})")
SLOT_MS = 600_000


def _date_in_name(text: str) -> dt.date | None:
    """The date a file name carries, or None when the digits are no calendar date."""
    try:
        return dt.date.fromisoformat(text)
    except ValueError:
        return None


def file_name(day: dt.date) -> str:
    """Published daily file name for a local day."""
    return f"sms-call-internet-mi-{day.isoformat()}.txt"


def read_raw(paths: Sequence[Path | str], squares: Sequence[int] | None = None, *, n_squares: int = 10_000,
             time_ranges: Sequence[tuple[int, int]] | None = None, on_out_of_range: str = "error",
             dropped: dict[str, int] | None = None) -> pl.DataFrame:
    """Reads daily Milan files, streaming, and sums internet over country codes.

    Args:
        paths: daily files (plain or .gz), any number.
        squares: keep only these square ids (None: all).
        n_squares: square ids must lie in 1..n_squares (the declared grid).
        time_ranges: allowed [lo, hi) UTC ms ranges (the configured segments); None allows any time.
        on_out_of_range: "error" (default) or "drop" for square ids outside the grid and times outside
            every range.
        dropped: if given, counts of dropped lines by reason are added to it: ``duplicate_lines`` (exact
            duplicates of an earlier line of the same file, all 8 fields equal by value, among the kept squares;
            always present) and, in "drop" mode, the out-of-range reasons.
    Returns:
        DataFrame (square_id int64, time_interval_ms int64, internet float64), one row per square and slot
        present in the files, sorted; squares whose lines all have a blank internet field get 0.
    Raises:
        PrepError: naming the file and line for a bad field (text that is no finite number, nan and NULL
            included), negative count, id or time out of range.
    """
    counts = dropped if dropped is not None else {}
    counts.setdefault("duplicate_lines", 0)
    parts: list[pl.DataFrame] = []
    keep = None if squares is None else pl.Series(list(squares), dtype=pl.Int64)
    for path in tqdm([Path(p) for p in paths], desc="milan files", unit="file", leave=False):
        lines: list[pl.DataFrame] = []  # the file's kept lines: a day's file holds each of its lines once
        for line0, df in iter_csv_batches(path, names=COLUMNS, types=_READ_TYPES, has_header=False,
                                          delimiter="\t"):
            df = _check_batch(path, line0, df, n_squares, time_ranges, on_out_of_range, counts)
            if keep is not None:
                df = df.filter(pl.col("square_id").is_in(keep.implode()))
            lines.append(df)
        if not lines:
            continue
        file_lines = pl.concat(lines)
        # Equal lines have equal hashes: all hashes distinct means no duplicate (the usual case, cheap); else
        # the exact comparison decides.
        hashes = file_lines.hash_rows(seed=0)
        unique = file_lines if hashes.n_unique() == hashes.len() else file_lines.unique()
        counts["duplicate_lines"] += file_lines.height - unique.height
        parts.append(unique.group_by("square_id", "time_interval_ms").agg(pl.col("internet").sum()))
    if not parts:
        return pl.DataFrame(schema={"square_id": pl.Int64, "time_interval_ms": pl.Int64, "internet": pl.Float64})
    return (pl.concat(parts).group_by("square_id", "time_interval_ms").agg(pl.col("internet").sum())
            .sort("square_id", "time_interval_ms"))


def _check_batch(path: Path, line0: int, df: pl.DataFrame, n_squares: int,
                 time_ranges: Sequence[tuple[int, int]] | None, on_out_of_range: str,
                 counts: dict[str, int]) -> pl.DataFrame:
    """Validates one batch; returns it with out-of-range lines removed when on_out_of_range == "drop"."""
    for col, what in (("square_id", "a square id"), ("time_interval_ms", "a time interval in ms")):
        i = first_bad(df[col].is_null())
        if i is not None:
            raise PrepError(f"{path}, line {line0 + i}, column {col!r}: expected {what}, found a blank field")
    i = first_bad((df["internet"] < 0).fill_null(False))
    if i is not None:
        raise PrepError(f"{path}, line {line0 + i}, column 'internet': expected a count >= 0, "
                        f"found {df['internet'][i]}")
    def outside_segments(frame: pl.DataFrame) -> pl.Series:
        t = frame["time_interval_ms"]
        inside = pl.Series([False] * frame.height)
        for lo, hi in time_ranges or []:
            inside = inside | ((t >= lo) & (t < hi))
        return ~inside

    checks = [("square_outside_grid", lambda f: ~f["square_id"].is_between(1, n_squares),
               f"expected a square id in 1..{n_squares} (the declared grid)", "square_id")]
    if time_ranges is not None:
        checks.append(("outside_segments", outside_segments, "expected a time inside a configured segment "
                       "(datasets.milan.split, local time)", "time_interval_ms"))
    for reason, test, expected, col in checks:
        bad = test(df)  # evaluated on the rows left by the previous check
        i = first_bad(bad)
        if i is None:
            continue
        if on_out_of_range == "error":
            raise PrepError(f"{path}, line {line0 + i}, column {col!r}: {expected}, found {df[col][i]}")
        counts[reason] = counts.get(reason, 0) + int(bad.sum())
        df = df.filter(~bad)
    return df


def _segment_ranges(days: list, tz: ZoneInfo) -> list[tuple[int, int]]:
    """UTC ms [lo, hi) of each configured local day."""
    out = []
    for d in days:
        lo = dt.datetime.combine(d.key, dt.time(0), tzinfo=tz)
        hi = dt.datetime.combine(d.key + dt.timedelta(days=1), dt.time(0), tzinfo=tz)
        out.append((int(lo.timestamp() * 1000), int(hi.timestamp() * 1000)))
    return out


def build(cfg: MilanConfig, paths: Sequence[Path]) -> RawTensor:
    """Builds the Milan crop tensor in raw units from daily files.

    Files whose name carries a date outside the configured segments are skipped unread (counted in the
    log). One source per date: two files dated the same day (``.txt`` and ``.txt.gz``) are an error naming
    both. A segment day without any line in the crop is an error naming the day, the files read and the
    expected file, unless ``allow_empty_days`` lists it.

    Args:
        cfg: datasets.milan.
        paths: raw daily files (globs already expanded).
    Returns:
        RawTensor with values (days, 144, rows, cols) of summed internet activity.
    """
    days = calendar_days(cfg.split, dataset="milan")
    by_date = {d.key: d for d in days}
    selected, skipped = [], 0
    sources: dict[dt.date, list[Path]] = {}
    for p in paths:
        m = _DATE_IN_NAME.search(Path(p).name)
        day = _date_in_name(m.group(1)) if m else None
        if m and day not in by_date:
            skipped += 1
            continue
        if day is not None:
            sources.setdefault(day, []).append(Path(p))
        selected.append(Path(p))
    for day, files in sorted(sources.items()):
        if len(files) > 1:
            raise PrepError(f"milan: day {day.isoformat()} has {len(files)} raw files: "
                            f"{', '.join(str(f) for f in files)}; expected one source per date (keep one of them)")
    log.info("milan: %d files selected, %d skipped (dates outside the configured segments)", len(selected), skipped)
    if not selected:
        raise PrepError(f"milan: none of the {len(paths)} raw files is dated inside the configured segments "
                        f"{cfg.split}; expected files like {file_name(days[0].key)}")
    crop = cfg.crop
    if not (0 <= crop.first_row and crop.first_row + crop.rows <= cfg.full_rows and 0 <= crop.first_col
            and crop.first_col + crop.cols <= cfg.full_cols and crop.rows > 0 and crop.cols > 0):
        raise PrepError(f"config key datasets.milan.crop: window {crop} does not fit the "
                        f"{cfg.full_rows}x{cfg.full_cols} grid (or is empty)")
    rr, cc = np.meshgrid(np.arange(crop.rows), np.arange(crop.cols), indexing="ij")
    ids = ((crop.first_row + rr) * cfg.full_cols + crop.first_col + cc + 1).ravel()
    tz = ZoneInfo(cfg.timezone)
    dropped: dict[str, int] = {}
    df = read_raw(selected, squares=ids.tolist(), n_squares=cfg.full_rows * cfg.full_cols,
                  time_ranges=_segment_ranges(days, tz), on_out_of_range=cfg.on_out_of_range, dropped=dropped)
    if df.height == 0:
        raise PrepError(f"milan: the crop (grid rows {crop.first_row}..{crop.first_row + crop.rows - 1}, columns "
                        f"{crop.first_col}..{crop.first_col + crop.cols - 1}) holds no line in the {len(selected)} "
                        f"selected file(s) {[p.name for p in selected][:3]}; expected square ids {ids.min()}..{ids.max()}")
    local = pl.from_epoch(df["time_interval_ms"], time_unit="ms").dt.replace_time_zone("UTC") \
        .dt.convert_time_zone(cfg.timezone)
    epoch_day = local.dt.date().cast(pl.Int64).to_numpy()
    slot = (local.dt.hour().cast(pl.Int64) * 6 + local.dt.minute().cast(pl.Int64) // 10).to_numpy()
    day_keys = np.array([(d.key - dt.date(1970, 1, 1)).days for d in days])
    day_index = np.searchsorted(day_keys, epoch_day)  # every time passed the segment check above
    sq = df["square_id"].to_numpy() - 1
    row = sq // cfg.full_cols - crop.first_row
    col = sq % cfg.full_cols - crop.first_col
    values = np.zeros((len(days), SLOTS_PER_DAY, crop.rows, crop.cols))
    np.add.at(values, (day_index, slot, row, col), df["internet"].to_numpy())
    present = set(day_index.tolist())
    allowed = allowed_empty(cfg)
    first_missing = next((d for d in days if d.index not in present and d.key not in allowed), days[0])
    empty = refuse_empty_days("milan", days, [d.index in present for d in days], allowed, selected,
                              what="line in the crop", expected=f"files such as {file_name(first_missing.key)} "
                              f"among the raw files")
    weekday = [d.key.weekday() for d in days]
    return RawTensor(
        dataset="milan", days=days, values=values, weekday=weekday, weekend=[w >= 5 for w in weekday],
        grid={"rows": crop.rows, "cols": crop.cols, "cell_m": cfg.cell_m, "first_row": crop.first_row,
              "first_col": crop.first_col, "full_rows": cfg.full_rows, "full_cols": cfg.full_cols,
              "square_id_of_row0_col0": int(ids[0]),
              "convention": "tensor row r = grid row first_row+r counted from the south; "
                            "square id = grid_row*full_cols + grid_col + 1"},
        crop={"rule": "fixed", "first_row": crop.first_row, "first_col": crop.first_col,
              "rows": crop.rows, "cols": crop.cols},
        dropped=dropped, notes={"files_skipped_outside_segments": skipped}, sources=describe_sources(selected),
        empty_days=empty)
