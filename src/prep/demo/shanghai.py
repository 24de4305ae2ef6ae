"""Shanghai Telecom demo: half-month workbooks `data_6.1~6.15.xlsx` ... with the published columns.

Base stations cluster around the city centre (a Gaussian core) with the rest spread over the declared box;
each user has a home station and, for most, a work station in the core. Session starts follow a
time-of-day profile of mobile internet use (low at night, evening peak); on working days employed users are
at work during office hours, on Saturdays and Sundays they stay near home, so the weekend shifts demand in
space. Sessions sit on stations only, so after 470 m gridding most cells are empty (docs/PROTOCOL.md §4: ~85% zero
cells in the crop). Real-world dirt is injected at the configured rates: blank and 0/0 locations, end
before start; sessions crossing midnight occur naturally.
"""
from __future__ import annotations

import calendar
import datetime as dt
from pathlib import Path

import numpy as np
import polars as pl
import xlsxwriter
from tqdm import tqdm

from prep.atomic import atomic_path
from prep.config import ShanghaiConfig
from prep.days import calendar_days
from prep.shanghai import COLUMNS, TIME_FORMAT

KM_PER_DEG_LAT = 111.195
# Session starts per hour of day (relative), piecewise linear: night trough, morning rise, evening peak.
_HOURS = np.array([0, 3, 6, 8, 12, 17, 21, 24], dtype=float)
_LEVEL = np.array([0.5, 0.15, 0.3, 1.1, 1.3, 1.2, 1.5, 0.5])
EMPLOYED_FRAC = 0.7  # users with a work station in the core


def file_name(first: dt.date, last: dt.date) -> str:
    """Published half-month file name, e.g. data_6.1~6.15.xlsx."""
    return f"data_{first.month}.{first.day}~{last.month}.{last.day}.xlsx"


def half_months(first: dt.date, last: dt.date) -> list[tuple[dt.date, dt.date]]:
    """Half-month periods (1st-15th, 16th-end of month) covering first..last."""
    out, d = [], dt.date(first.year, first.month, 1)
    while d <= last:
        end_day = calendar.monthrange(d.year, d.month)[1]
        for a, b in ((1, 15), (16, end_day)):
            lo, hi = dt.date(d.year, d.month, a), dt.date(d.year, d.month, b)
            if hi >= first and lo <= last:
                out.append((lo, hi))
        d = dt.date(d.year + (d.month == 12), d.month % 12 + 1, 1)
    return out


def simulate(cfg: ShanghaiConfig) -> pl.DataFrame:
    """Deterministic demo sessions (before dirt): DataFrame (start, end, latitude, longitude, user id)."""
    demo = cfg.demo
    rng = np.random.default_rng(demo.seed)
    km_lon = KM_PER_DEG_LAT * np.cos(np.radians(demo.centre_lat))
    n_core = int(round(demo.n_base_stations * demo.core_share))
    n_out = demo.n_base_stations - n_core
    bs_lat = np.concatenate([demo.centre_lat + rng.normal(0, demo.centre_sigma_km, n_core) / KM_PER_DEG_LAT,
                             rng.uniform(cfg.lat_min, cfg.lat_max, n_out)])
    bs_lon = np.concatenate([demo.centre_lon + rng.normal(0, demo.centre_sigma_km, n_core) / km_lon,
                             rng.uniform(cfg.lon_min, cfg.lon_max, n_out)])
    bs_lat = np.clip(bs_lat, cfg.lat_min, cfg.lat_max).round(6)
    bs_lon = np.clip(bs_lon, cfg.lon_min, cfg.lon_max).round(6)
    u = demo.n_users
    home = rng.integers(0, demo.n_base_stations, u)
    employed = rng.random(u) < EMPLOYED_FRAC
    work = np.where(employed, rng.integers(0, n_core, u), home)
    user_ids = np.array([f"{v:012x}" for v in rng.integers(0, 2 ** 48, u)])
    mid = (np.arange(144) + 0.5) / 6.0
    p_slot = np.interp(mid, _HOURS, _LEVEL)
    p_slot /= p_slot.sum()
    office = (mid >= 9.0) & (mid < 18.0)
    days = calendar_days(cfg.split, dataset="shanghai")
    parts = []
    for day in days:
        weekend = day.key.weekday() >= 5
        k = rng.poisson(demo.sessions_per_user_day * (0.85 if weekend else 1.0), u)
        user = np.repeat(np.arange(u), k)
        slot = rng.choice(144, size=user.size, p=p_slot)
        sec = slot * 600 + rng.integers(0, 600, user.size)
        r = rng.random(user.size)
        at_work = employed[user] & office[slot] & (r < 0.8) & (not weekend)
        roam = ~at_work & (r > 0.85)
        station = np.where(at_work, work[user], home[user])
        station = np.where(roam, rng.integers(0, n_core, user.size), station)
        midnight = np.datetime64(day.key.isoformat(), "ms")
        start = midnight + (sec * 1000).astype("timedelta64[ms]")
        dur = (1000 * np.maximum(1, rng.exponential(demo.mean_duration_min * 60.0, user.size)).astype(np.int64)) \
            .astype("timedelta64[ms]")
        parts.append(pl.DataFrame({"start": start, "end": start + dur, "latitude": bs_lat[station],
                                   "longitude": bs_lon[station], "user id": user_ids[user]}))
    return pl.concat(parts).sort("start", "user id")


def add_dirt(sessions: pl.DataFrame, cfg: ShanghaiConfig) -> pl.DataFrame:
    """Injects the real data's dirt: blank and 0/0 locations, end before start (fractions from config)."""
    demo = cfg.demo
    rng = np.random.default_rng([demo.seed, 1])
    n = sessions.height
    kind = rng.random(n)
    a, b = demo.missing_location_frac, demo.missing_location_frac + demo.zero_location_frac
    c = b + demo.end_before_start_frac
    missing, zero, reverse = kind < a, (kind >= a) & (kind < b), (kind >= b) & (kind < c)
    back = pl.Series(rng.integers(60, 3600, n) * 1_000_000).cast(pl.Duration("us"))
    return sessions.with_columns(
        pl.when(pl.Series(missing)).then(None).when(pl.Series(zero)).then(0.0).otherwise(pl.col("latitude"))
        .alias("latitude"),
        pl.when(pl.Series(missing)).then(None).when(pl.Series(zero)).then(0.0).otherwise(pl.col("longitude"))
        .alias("longitude"),
        pl.when(pl.Series(reverse)).then(pl.col("start") - back).otherwise(pl.col("end")).alias("end"))


def generate(cfg: ShanghaiConfig, out_dir: Path) -> list[Path]:
    """Writes the half-month demo workbooks into `out_dir`; returns their paths."""
    sessions = add_dirt(simulate(cfg), cfg)
    days = calendar_days(cfg.split, dataset="shanghai")
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for lo, hi in tqdm(half_months(days[0].key, days[-1].key), desc="shanghai demo files", unit="file"):
        part = sessions.filter(pl.col("start").dt.date().is_between(lo, hi))
        table = part.select(
            (pl.col("start").dt.year() * 100 + pl.col("start").dt.month()).alias("month"),
            pl.col("start").dt.strftime("%Y%m%d").cast(pl.Int64).alias("date"),
            pl.col("start").dt.strftime(TIME_FORMAT).alias("start time"),
            pl.col("end").dt.strftime(TIME_FORMAT).alias("end time"),
            "latitude", "longitude", "user id")
        assert table.columns == list(COLUMNS)
        path = out_dir / file_name(lo, hi)
        with atomic_path(path) as tmp:
            _write_xlsx(tmp, table)
        written.append(path)
    return written


def _write_xlsx(path: Path, table: pl.DataFrame) -> None:
    """One sheet: a header row of the table's column names, one row per session (blank cells for nulls)."""
    wb = xlsxwriter.Workbook(str(path), {"constant_memory": True})
    wb.set_properties({"created": dt.datetime(2014, 12, 1)})  # fixed: identical bytes on every run
    ws = wb.add_worksheet("Sheet1")
    ws.write_row(0, 0, table.columns)
    write_row = ws.write_row
    for i, row in enumerate(table.iter_rows(), start=1):
        write_row(i, 0, row)
    wb.close()
