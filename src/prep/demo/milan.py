"""Milan demo: daily `sms-call-internet-mi-YYYY-MM-DD.txt` files for the crop's squares, driven by real data.

Model (all inputs are the real files in prep/assets/milan, see its PROVENANCE.md):
    mean_g(t) = total_g / N * (B(t) + m_g * (A(t) - B(t)))
where total_g is square g's real two-month total, N = 8928 slots in those two months, A and B are the real
10-minute series of squares 4556 (evening/night heavy) and 5161 (office hours), each scaled to mean 1 over
the two months and taken at the SAME dates as the generated day (so the weekly cycle and the Christmas /
New-Year week are the real ones), and m_g in [0, 1] is fitted per square by least squares to the 81 real
full-grid frames at their timestamps. Cells thus have different daily profiles and the hotspots move
through the day. Each value gets a per-(day, square) level and a per-(slot, square) log-normal factor and is
split over country codes (39 carries most of it; extra codes carry small shares or only SMS/calls with a
blank internet field), as in the published files.
"""
from __future__ import annotations

import datetime as dt
from importlib import resources
from pathlib import Path

import numpy as np
import polars as pl
from tqdm import tqdm

from prep.atomic import atomic_path
from prep.config import MilanConfig
from prep.days import calendar_days
from prep.milan import SLOT_MS, file_name
from prep.rawio import PrepError

_EXTRA_CODES = np.array([0, 1, 7, 33, 34, 40, 41, 44, 48, 49, 86, 212, 355, 380, 420, 4470, 33650])
_MAX_EXTRA = 4
_LOCAL_OFFSET_MS = 3_600_000  # the shipped series start at local midnight CET = UTC+1 (no DST change Nov-Jan)


def load_assets() -> dict[str, np.ndarray]:
    """Loads the shipped real Milan files.

    Returns:
        dict with totals (100, 100) indexed [grid_row_from_south, grid_col]; series_time (8928,);
        series_a / series_b (8928,) for squares 4556 / 5161; frames (81, 40, 40), frames_time (81,),
        frames_first_row, frames_first_col.
    """
    base = resources.files("prep") / "assets" / "milan"
    tot = pl.read_csv(str(base / "square_totals_2mo.csv")).sort("square_id")
    if tot.height != 10_000 or tot["square_id"].to_list() != list(range(1, 10_001)):
        raise PrepError(f"{base / 'square_totals_2mo.csv'}: expected square ids 1..10000")
    with np.load(str(base / "series_4556_5161.npz")) as s, np.load(str(base / "frames_r30-69_c30-69.npz")) as f:
        return {"totals": tot["internet"].to_numpy().reshape(100, 100), "series_time": s["time_interval_ms"],
                "series_a": s["internet_4556"].astype(np.float64), "series_b": s["internet_5161"].astype(np.float64),
                "frames": f["internet"].astype(np.float64), "frames_time": f["time_interval_ms"],
                "frames_first_row": int(f["first_row"]), "frames_first_col": int(f["first_col"])}


def fit_profile_mix(frames: np.ndarray, frames_time: np.ndarray, level: np.ndarray, series_time: np.ndarray,
                    a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per-square weight m of profile A against B, fitted to real frames by least squares.

    Args:
        frames: (K, G) real values of the squares at K timestamps.
        frames_time: (K,) timestamps (ms) of the frames; each must be in `series_time`.
        level: (G,) mean value per slot of each square (two-month total / number of slots).
        series_time, a, b: (N,) the two real profiles, scaled to mean 1.
    Returns:
        (G,) m clipped to [0, 1]: frames ~ level * (b + m (a - b)).
    """
    idx = np.searchsorted(series_time, frames_time)
    if np.any(idx >= len(series_time)) or np.any(series_time[np.minimum(idx, len(series_time) - 1)] != frames_time):
        raise PrepError("milan demo assets: a frame timestamp is missing from the shipped series")
    d = a[idx] - b[idx]  # (K,)
    y = frames / level[None, :] - b[idx][:, None]
    return np.clip((d[:, None] * y).sum(axis=0) / float(np.dot(d, d)), 0.0, 1.0)


def generate(cfg: MilanConfig, out_dir: Path) -> list[Path]:
    """Writes one raw daily file per configured day into `out_dir`.

    Args:
        cfg: datasets.milan (crop, split, demo settings).
        out_dir: destination directory (created).
    Returns:
        The written file paths.
    """
    assets = load_assets()
    crop, demo = cfg.crop, cfg.demo
    fr0, fc0 = assets["frames_first_row"], assets["frames_first_col"]
    fh, fw = assets["frames"].shape[1:]
    if not (fr0 <= crop.first_row and crop.first_row + crop.rows <= fr0 + fh and fc0 <= crop.first_col
            and crop.first_col + crop.cols <= fc0 + fw):
        raise PrepError(f"config key datasets.milan.crop: the demo ships real frames for grid rows {fr0}..{fr0 + fh - 1}"
                        f" and columns {fc0}..{fc0 + fw - 1} only; found crop {crop} (use source: raw for others)")
    rs = slice(crop.first_row, crop.first_row + crop.rows)
    cs = slice(crop.first_col, crop.first_col + crop.cols)
    totals = assets["totals"][rs, cs].ravel()
    t_series = assets["series_time"]
    level = totals / len(t_series)
    a = assets["series_a"] / assets["series_a"].mean()
    b = assets["series_b"] / assets["series_b"].mean()
    frames = assets["frames"][:, rs.start - fr0: rs.stop - fr0, cs.start - fc0: cs.stop - fc0]
    mix = fit_profile_mix(frames.reshape(len(frames), -1), assets["frames_time"], level, t_series, a, b)
    rr, cc = np.meshgrid(np.arange(rs.start, rs.stop), np.arange(cs.start, cs.stop), indexing="ij")
    squares = (rr * cfg.full_cols + cc + 1).ravel()
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for day in tqdm(calendar_days(cfg.split, dataset="milan"), desc="milan demo days", unit="day"):
        midnight_utc = int(dt.datetime.combine(day.key, dt.time(0), tzinfo=dt.UTC).timestamp() * 1000) \
            - _LOCAL_OFFSET_MS
        pos = int(np.searchsorted(t_series, midnight_utc))
        if pos + 144 > len(t_series) or t_series[pos] != midnight_utc:
            raise PrepError(f"datasets.milan.split: the demo has real series for 2013-11-01..2014-01-01 only; "
                            f"found day {day.label}")
        rng = np.random.default_rng([demo.seed, day.key.toordinal()])
        mean = level[None, :] * (b[pos:pos + 144, None] + mix[None, :] * (a - b)[pos:pos + 144, None])
        noise = rng.normal(0.0, demo.noise_sigma, mean.shape) - demo.noise_sigma ** 2 / 2
        day_level = rng.normal(0.0, demo.day_level_sigma, (1, mean.shape[1])) - demo.day_level_sigma ** 2 / 2
        values = mean * np.exp(noise + day_level)  # (144, G)
        times = midnight_utc + SLOT_MS * np.arange(144, dtype=np.int64)
        table = _country_rows(rng, values, times, squares, demo.extra_codes_mean, demo.blank_internet_frac)
        path = out_dir / file_name(day.key)
        with atomic_path(path) as tmp:
            table.write_csv(tmp, separator="\t", include_header=False, null_value="", float_precision=4)
        written.append(path)
    return written


def _country_rows(rng: np.random.Generator, values: np.ndarray, times: np.ndarray, squares: np.ndarray,
                  extra_mean: float, blank_frac: float) -> pl.DataFrame:
    """Splits (144, G) internet values over country codes; returns the day's lines in published column order."""
    n_t, n_g = values.shape
    t_idx, g_idx = np.meshgrid(np.arange(n_t), np.arange(n_g), indexing="ij")
    t_idx, g_idx, v = t_idx.ravel(), g_idx.ravel(), values.ravel()
    n_extra = np.minimum(rng.poisson(extra_mean, v.size), _MAX_EXTRA)
    rep = np.repeat(np.arange(v.size), n_extra)  # parent cell-slot of each extra line
    # distinct extra codes per cell-slot: a random start, then steps of 5 through a list of prime length
    rank = np.arange(rep.size) - np.repeat(np.cumsum(n_extra) - n_extra, n_extra)
    offset = rng.integers(0, len(_EXTRA_CODES), v.size)
    extra_code = _EXTRA_CODES[(np.repeat(offset, n_extra) + rank * 5) % len(_EXTRA_CODES)]
    share = rng.uniform(0.002, 0.03, rep.size)
    blank = rng.random(rep.size) < blank_frac
    share[blank] = 0.0
    main_share = 1.0 - np.bincount(rep, weights=share, minlength=v.size)
    n_lines = v.size + rep.size
    parent = np.concatenate([np.arange(v.size), rep])
    code = np.concatenate([np.full(v.size, 39), extra_code])
    internet = np.concatenate([v * main_share, v[rep] * share])
    internet_blank = np.concatenate([np.zeros(v.size, bool), blank])
    sms = np.concatenate([v * rng.uniform(0.02, 0.06, v.size), v[rep] * rng.uniform(0.0, 0.01, rep.size)])
    calls = np.concatenate([v * rng.uniform(0.01, 0.04, v.size), v[rep] * rng.uniform(0.0, 0.005, rep.size)])
    quiet = rng.random(n_lines) < 0.3  # lines without SMS or call activity leave those fields blank
    df = pl.DataFrame({
        "square_id": squares[g_idx[parent]], "time_interval_ms": times[t_idx[parent]], "country_code": code,
        "sms_in": np.where(quiet, np.nan, sms), "sms_out": np.where(quiet, np.nan, sms * 0.8),
        "call_in": np.where(quiet, np.nan, calls), "call_out": np.where(quiet, np.nan, calls * 1.1),
        "internet": np.where(internet_blank, np.nan, internet)})
    df = df.with_columns(pl.col(c).fill_nan(None) for c in ("sms_in", "sms_out", "call_in", "call_out", "internet"))
    assert df.height == n_lines
    return df.sort("square_id", "time_interval_ms", "country_code")
