"""Shanghai Telecom: raw reader (half-month .xlsx files or CSV exports) and crop tensor builder.

Raw format: columns month, date, start time, end time, latitude, longitude, user id; times
`%Y-%m-%d %H:%M:%S` (local time) or Excel date cells. A coordinate is a finite number or a blank cell (a missing
location); other text (`nan`, `NA`, `NULL`, ...) is an error naming the file, row and text. Rows with a missing
(blank) or 0/0 location and sessions that
end before they start are real: they are dropped and counted, as are exact duplicate rows (one source per
session, across files). Sessions crossing midnight are kept and counted at their start. Every configured day
must have a session unless ``allow_empty_days`` lists it. Demand = session starts per 470 m cell and 10-min
slot, trailing 3-slot mean (slot t and the two before it, never a later one), in the 20 x 20 window with the
most training starts.
"""
from __future__ import annotations

import calendar
import datetime as dt
import logging
from collections.abc import Iterator, Sequence
from pathlib import Path

import numpy as np
import polars as pl
import pyarrow as pa
from tqdm import tqdm

from prep.config import ShanghaiConfig
from prep.days import allowed_empty, calendar_days, refuse_empty_days
from prep.grid import LatLonGrid, densest_window
from prep.rawio import PrepError, check_not_empty, describe_sources, first_bad, iter_csv_batches
from prep.tensor import SLOTS_PER_DAY, RawTensor, train_index

log = logging.getLogger(__name__)

COLUMNS = ("month", "date", "start time", "end time", "latitude", "longitude", "user id")
TIME_FORMAT = "%Y-%m-%d %H:%M:%S"
_SESSION_SCHEMA = {"user_id": pl.String, "start": pl.Datetime("us"), "end": pl.Datetime("us"),
                   "latitude": pl.Float64, "longitude": pl.Float64}


def _norm(name: str) -> str:
    return " ".join(str(name).strip().lower().replace("_", " ").split())


def _raw_tables(path: Path) -> Iterator[tuple[str, int, pl.DataFrame]]:
    """Yields (where, first_row_number, all-text table) per sheet of an Excel file or per CSV batch."""
    if not path.is_file():
        raise PrepError(f"{path}: no such file")
    if path.suffix.lower() in (".xlsx", ".xlsm", ".xls"):
        check_not_empty(path, f"an Excel workbook with the columns {list(COLUMNS)}")
        try:
            sheets = pl.read_excel(path, sheet_id=0, infer_schema_length=0, engine="calamine")
        except Exception as exc:  # the Excel engine raises its own exception types
            raise PrepError(f"{path}: cannot read as an Excel workbook ({exc})") from exc
        for name, df in sheets.items():
            if df.width == 0 or df.height == 0:
                continue
            df = df.rename({c: _norm(c) for c in df.columns})
            missing = [c for c in COLUMNS if c not in df.columns]
            if missing:
                raise PrepError(f"{path}, sheet {name!r}, row 1: missing column(s) {missing}; expected "
                                f"{list(COLUMNS)}, found {df.columns}")
            yield f"{path}, sheet {name!r}", 2, df.select(COLUMNS)
    else:
        for line0, df in iter_csv_batches(path, names=COLUMNS, types={c: pa.string() for c in COLUMNS},
                                          has_header=True):
            yield str(path), line0, df


def _parse_time(col: pl.Series) -> pl.Series:
    text = col.str.strip_chars()
    full = text.str.strptime(pl.Datetime("us"), TIME_FORMAT, strict=False)
    # Excel date cells read as text may carry fractional seconds.
    frac = text.str.strptime(pl.Datetime("us"), "%Y-%m-%d %H:%M:%S%.f", strict=False)
    return full.fill_null(frac)


def workbook_name(day: dt.date) -> str:
    """The published half-month workbook holding `day`, e.g. data_11.1~11.15.xlsx."""
    first, last = (1, 15) if day.day <= 15 else (16, calendar.monthrange(day.year, day.month)[1])
    return f"data_{day.month}.{first}~{day.month}.{last}.xlsx"


def iter_sessions(paths: Sequence[Path | str], *, dropped: dict[str, int] | None = None,
                  notes: dict[str, int] | None = None) -> Iterator[tuple[str, np.ndarray, pl.DataFrame]]:
    """Streams cleaned sessions file by file (sheet by sheet, or batch by batch for CSV).

    One source per session: a row equal in every column to a row read before it (in the same or an earlier
    file, e.g. a half-month workbook present twice under two names) is dropped and counted. Rows are compared
    by value (times and coordinates parsed, the other columns as trimmed text), so an .xlsx and its CSV
    export match. Only a 64-bit hash of each kept row is held, not the rows (two different rows share a hash
    with a probability of about 1e-6 over the 7.2M published rows).

    Args:
        paths: .xlsx files or CSV exports with the published columns.
        dropped: counts of dropped rows by reason are added to it (duplicate_rows, always present;
            missing_location, zero_location, end_before_start).
        notes: counts of kept rows worth knowing are added to it (crossing_midnight: counted at their start).
    Yields:
        (where, rows, sessions): "file[, sheet]", (n,) row numbers in that file/sheet, DataFrame (user_id,
        start, end, latitude, longitude).
    Raises:
        PrepError: missing file or column, unparseable time, non-numeric coordinate, naming file and row.
    """
    counts = dropped if dropped is not None else {}
    counts.setdefault("duplicate_rows", 0)
    kept = notes if notes is not None else {}
    seen = pl.Series("hash", [], dtype=pl.UInt64)  # row hashes of every row read so far
    for path in tqdm([Path(p) for p in paths], desc="shanghai files", unit="file", leave=False):
        for where, row0, df in _raw_tables(path):
            start, end = _parse_time(df["start time"]), _parse_time(df["end time"])
            for name, raw, parsed in (("start time", df["start time"], start), ("end time", df["end time"], end)):
                blank = raw.is_null() | (raw.str.strip_chars() == "")
                i = first_bad(parsed.is_null() & ~(blank if name == "end time" else pl.Series([False] * df.height)))
                if i is not None:
                    raise PrepError(f"{where}, row {row0 + i}, column {name!r}: expected a time like "
                                    f"2014-06-01 08:30:00, found {raw[i]!r}")
            coords = {}
            for name in ("latitude", "longitude"):
                raw = df[name]
                val = raw.str.strip_chars().cast(pl.Float64, strict=False)
                blank = raw.is_null() | (raw.str.strip_chars() == "")
                # Only a blank cell is a missing location: text such as nan, NA or NULL is no number (a cast
                # reads nan and inf as floats, so the check is on finite values).
                i = first_bad(~val.is_finite().fill_null(False) & ~blank)
                if i is not None:
                    raise PrepError(f"{where}, row {row0 + i}, column {name!r}: expected a number, found {raw[i]!r}")
                coords[name] = val
            lat, lon = coords["latitude"], coords["longitude"]
            row_hash = pl.DataFrame({"month": df["month"].str.strip_chars(), "date": df["date"].str.strip_chars(),
                                     "start": start, "end": end, "latitude": lat, "longitude": lon,
                                     "user": df["user id"].str.strip_chars()}).hash_rows(seed=0)
            duplicate = ~row_hash.is_first_distinct() | row_hash.is_in(seen.implode())
            seen = pl.concat([seen, row_hash.filter(~duplicate).rename("hash")])
            counts["duplicate_rows"] += int(duplicate.sum())
            missing = ~duplicate & (lat.is_null() | lon.is_null())
            zero = ~duplicate & ~missing & (lat == 0) & (lon == 0)
            reversed_ = ~duplicate & ~missing & ~zero & end.is_not_null() & (end < start)
            keep = ~(duplicate | missing | zero | reversed_)
            counts["missing_location"] = counts.get("missing_location", 0) + int(missing.sum())
            counts["zero_location"] = counts.get("zero_location", 0) + int(zero.sum())
            counts["end_before_start"] = counts.get("end_before_start", 0) + int(reversed_.sum())
            out = pl.DataFrame({"user_id": df["user id"], "start": start, "end": end, "latitude": lat,
                                "longitude": lon}).filter(keep)
            crossing = (out["end"].dt.date() > out["start"].dt.date()).fill_null(False)
            kept["crossing_midnight"] = kept.get("crossing_midnight", 0) + int(crossing.sum())
            yield where, row0 + np.flatnonzero(keep.to_numpy()), out


def read_raw(paths: Sequence[Path | str], *, dropped: dict[str, int] | None = None,
             notes: dict[str, int] | None = None) -> pl.DataFrame:
    """All cleaned sessions (user_id, start, end, latitude, longitude) of the given files.

    For the full dataset prefer `build`, which reduces each file to counts before reading the next.
    """
    parts = [df for _, _, df in iter_sessions(paths, dropped=dropped, notes=notes)]
    return pl.concat(parts) if parts else pl.DataFrame(schema=_SESSION_SCHEMA)


def trailing_mean(values: np.ndarray, window: int, day_keys: Sequence[dt.date]) -> np.ndarray:
    """Trailing mean over `window` slots (slot t and the window-1 before it) along a continuous timeline.

    Args:
        values: (D, T, R, C) counts.
        window: number of slots.
        day_keys: (D,) dates; the timeline restarts (no earlier slots) where a day does not follow the
            previous one, and the mean is over the slots available there.
    Returns:
        (D, T, R, C) float64.
    """
    d, t = values.shape[:2]
    out = np.empty_like(values, dtype=np.float64)
    start = 0
    for k in range(1, d + 1):
        if k == d or (day_keys[k] - day_keys[k - 1]).days != 1:
            flat = values[start:k].reshape((k - start) * t, *values.shape[2:]).astype(np.float64)
            c = np.concatenate([np.zeros((1, *flat.shape[1:])), np.cumsum(flat, axis=0)])
            idx = np.arange(1, flat.shape[0] + 1)
            lo = np.maximum(idx - window, 0)
            n = (idx - lo).reshape(-1, *([1] * (flat.ndim - 1)))
            out[start:k] = ((c[idx] - c[lo]) / n).reshape(k - start, t, *values.shape[2:])
            start = k
    return out


def build(cfg: ShanghaiConfig, paths: Sequence[Path]) -> RawTensor:
    """Builds the Shanghai crop tensor in raw units (session starts per slot, trailing mean)."""
    days = calendar_days(cfg.split, dataset="shanghai")
    grid = LatLonGrid(lat_min=cfg.lat_min, lat_max=cfg.lat_max, lon_min=cfg.lon_min, lon_max=cfg.lon_max,
                      cell_m=cfg.cell_m)
    n_rows, n_cols = grid.shape
    first, last = days[0].key, days[-1].key
    first_ord = first.toordinal()
    lut = np.full(last.toordinal() - first_ord + 1, -1, dtype=np.int64)  # date ordinal -> tensor day index
    for d in days:
        lut[d.key.toordinal() - first_ord] = d.index
    dropped: dict[str, int] = {}
    notes: dict[str, int] = {}
    parts = []
    for where, rows, sessions in iter_sessions(paths, dropped=dropped, notes=notes):
        lat, lon = sessions["latitude"].to_numpy(), sessions["longitude"].to_numpy()
        start_date = sessions["start"].dt.date()
        inside = grid.inside(lat, lon)
        day_ord = (start_date.cast(pl.Int64).to_numpy() + dt.date(1970, 1, 1).toordinal())
        rel = day_ord - first_ord
        in_seg = (rel >= 0) & (rel < len(lut))
        in_seg[in_seg] = lut[rel[in_seg]] >= 0
        for reason, ok, expected, found in (
                ("location_outside_grid", inside, f"expected a location inside lat {cfg.lat_min}..{cfg.lat_max}, "
                 f"lon {cfg.lon_min}..{cfg.lon_max} (datasets.shanghai)", lambda i: f"{lat[i]}, {lon[i]}"),
                ("outside_segments", in_seg, f"expected a start inside a configured segment ({first}..{last})",
                 lambda i: str(sessions["start"][i]))):
            i = first_bad(~ok)
            if i is None:
                continue
            if cfg.on_out_of_range == "error":
                raise PrepError(f"{where}, row {rows[i]}: {expected}, found {found(i)} "
                                f"(datasets.shanghai.on_out_of_range: drop would drop such rows)")
            dropped[reason] = dropped.get(reason, 0) + int((~ok).sum())
        keep = inside & in_seg
        r, c = grid.cells(lat[keep], lon[keep])
        start = sessions["start"].filter(pl.Series(keep))
        slot = (start.dt.hour().cast(pl.Int64) * 6 + start.dt.minute().cast(pl.Int64) // 10).to_numpy()
        di = lut[rel[keep]]
        parts.append(pl.DataFrame({"day": di, "slot": slot, "row": r, "col": c})
                     .group_by("day", "slot", "row", "col").len())
    counts = pl.concat(parts).group_by("day", "slot", "row", "col").agg(pl.col("len").sum()) if parts else None
    if counts is None or counts.height == 0:
        raise PrepError(f"shanghai: no valid session inside the declared grid and the configured segments in "
                        f"{len(paths)} file(s)")
    per_day = np.bincount(counts["day"].to_numpy(), weights=counts["len"].to_numpy(), minlength=len(days))
    allowed = allowed_empty(cfg)
    first_missing = next((d for d in days if per_day[d.index] == 0 and d.key not in allowed), days[0])
    empty = refuse_empty_days("shanghai", days, (per_day > 0).tolist(), allowed, paths, what="session",
                              expected=f"sessions on every configured day (e.g. the half-month workbook "
                              f"{workbook_name(first_missing.key)} among the raw files)")
    train_days = set(train_index(days).tolist())
    tr = counts.filter(pl.col("day").is_in(list(train_days))).group_by("row", "col").agg(pl.col("len").sum())
    totals = np.zeros((n_rows, n_cols))
    totals[tr["row"].to_numpy(), tr["col"].to_numpy()] = tr["len"].to_numpy()
    r0, c0, total = densest_window(totals, cfg.crop.rows, cfg.crop.cols)
    if total == 0:
        raise PrepError(f"shanghai: the densest {cfg.crop.rows}x{cfg.crop.cols} window holds no training session "
                        f"(empty crop)")
    win = counts.filter(pl.col("row").is_between(r0, r0 + cfg.crop.rows - 1)
                        & pl.col("col").is_between(c0, c0 + cfg.crop.cols - 1))
    starts = np.zeros((len(days), SLOTS_PER_DAY, cfg.crop.rows, cfg.crop.cols))
    starts[win["day"].to_numpy(), win["slot"].to_numpy(), win["row"].to_numpy() - r0,
           win["col"].to_numpy() - c0] = win["len"].to_numpy()
    values = trailing_mean(starts, cfg.window_slots, [d.key for d in days])
    lat0, lon0 = grid.centre(np.array([r0]), np.array([c0]))
    weekday = [d.key.weekday() for d in days]
    log.info("shanghai: window rows %d..%d, cols %d..%d (%d training starts); dropped %s", r0,
             r0 + cfg.crop.rows - 1, c0, c0 + cfg.crop.cols - 1, total, dropped)
    return RawTensor(
        dataset="shanghai", days=days, values=values, weekday=weekday, weekend=[w >= 5 for w in weekday],
        grid={"rows": cfg.crop.rows, "cols": cfg.crop.cols, "cell_m": cfg.cell_m, "first_row": r0,
              "first_col": c0, "full_rows": n_rows, "full_cols": n_cols, "lat_min": cfg.lat_min,
              "lon_min": cfg.lon_min, "centre_of_row0_col0": [float(lat0[0]), float(lon0[0])],
              "convention": "rows northward from lat_min, cols eastward from lon_min, local equirectangular"},
        crop={"rule": "densest_train", "first_row": r0, "first_col": c0, "rows": cfg.crop.rows,
              "cols": cfg.crop.cols, "train_starts": int(total), "window_slots": cfg.window_slots},
        dropped=dropped, notes=notes, sources=describe_sources(list(paths)), empty_days=empty)
