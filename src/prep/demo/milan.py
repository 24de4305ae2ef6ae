"""Milan demo: daily `sms-call-internet-mi-YYYY-MM-DD.txt` files for the crop's squares, driven by real data.

Model (all inputs are the real files in prep/assets/milan, see its PROVENANCE.md):
    mean_g(t) = total_g / N * p_g(t) * F_g(t)
where total_g is square g's real two-month total and N = 8928 slots in those two months.

p_g is the square's daily profile, built from A and B, the real 10-minute series of squares 4556 (evening/night
heavy) and 5161 (office hours), each scaled to mean 1 over the two months and taken at the SAME dates as the
generated day (so the weekly cycle and the Christmas / New-Year week are the real ones):
    p_g = (1 - f_g) * (B + m_g (A - B)) + f_g * daymean(B + m_g (A - B)),
m_g in [0, 1] is how much of profile A the square follows and f_g in [0, 1] how much of its within-day swing it
damps (the central squares swing less between night and day than the two profile squares; a damped profile
keeps the square's daily totals, hence its weekly cycle and holiday week). Both are fitted per square by least
squares to the 81 real full-grid frames at their timestamps (`fit_profile_mix`).

F_g(t) = exp(sigma X_g(t)) / c_g is a residual field: X is a unit-variance Gaussian field, Gaussian-smoothed in
space (`field_smooth_cells`) and AR(1) in time (`field_tau_slots`), drawn once for the whole two-month span
from the seed, and c_g makes the square's two-month total exactly total_g again. It stands for what two
profiles cannot: squares that drift away from their profile and back over a few hours, so the hotspots
migrate as in the real frames. Its persistence is fitted to the two real 62-day series (`fit_persistence`),
its amplitude and spatial scale to the real frames' residuals (`fit_residual_field`); config.yaml holds the
fitted values and tests/test_demo_milan.py refits them.

Each value then gets a per-(day, square) level and a per-(slot, square) log-normal factor and is split over
country codes (39 carries most of it; extra codes carry small shares or only SMS/calls with a blank internet
field), as in the published files.
"""
from __future__ import annotations

import datetime as dt
from importlib import resources
from pathlib import Path

import numpy as np
import polars as pl
from scipy.ndimage import gaussian_filter, gaussian_filter1d
from scipy.optimize import least_squares
from scipy.signal import lfilter
from tqdm import tqdm

from prep.atomic import atomic_path
from prep.config import MilanConfig
from prep.days import calendar_days
from prep.milan import SLOT_MS, file_name
from prep.rawio import PrepError

_EXTRA_CODES = np.array([0, 1, 7, 33, 34, 40, 41, 44, 48, 49, 86, 212, 355, 380, 420, 4470, 33650])
_MAX_EXTRA = 4
_LOCAL_OFFSET_MS = 3_600_000  # the shipped series start at local midnight CET = UTC+1 (no DST change Nov-Jan)
_SLOTS = 144
_FIELD_STREAM = 0  # random stream of the residual field: [seed, 0]; each day's draws use [seed, date ordinal]
_TRUNCATE = 4.0  # Gaussian kernels are cut at 4 standard deviations (scipy's default)
_DAMP_GRID = np.linspace(0.0, 1.0, 51)  # candidate damping f_g, steps of 0.02
# Fit of the residual field to the frames: increments at every lag within each run of consecutive frames,
# between squares 0..4 apart (beyond 4 the real increments are nearly uncorrelated).
FIT_OFFSETS = (0, 1, 2, 3, 4)
# Fit of the persistence to the two series: the 50 days 2013-11-01..12-20 (before the Christmas period, whose
# days are not like the weekday means), covariances up to 3 days apart.
PERSISTENCE_DAYS = 50
PERSISTENCE_MAX_LAG = 432


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


def day_means(x: np.ndarray) -> np.ndarray:
    """Each local day's mean of a series of whole days (144 slots from local midnight), repeated over the day.

    Args:
        x: (N, ...) with N a multiple of 144.
    Returns:
        Array of x's shape.
    """
    if x.shape[0] % _SLOTS:
        raise PrepError(f"milan demo: a series of {x.shape[0]} slots is not a whole number of days")
    days = x.reshape(x.shape[0] // _SLOTS, _SLOTS, *x.shape[1:]).mean(axis=1)
    return np.repeat(days, _SLOTS, axis=0)


def profiles(a: np.ndarray, b: np.ndarray, mix: np.ndarray, damp: np.ndarray) -> np.ndarray:
    """Daily profiles p_g = (1 - f_g) (B + m_g (A - B)) + f_g daymean(B + m_g (A - B)).

    Args:
        a, b: (N,) the two real profiles (whole days), scaled to mean 1.
        mix, damp: (G,) m_g and f_g.
    Returns:
        (N, G) profiles; each has mean 1 and the daily means of B + m_g (A - B).
    """
    pa = a[:, None] * (1.0 - damp) + day_means(a)[:, None] * damp
    pb = b[:, None] * (1.0 - damp) + day_means(b)[:, None] * damp
    return pb + mix * (pa - pb)


def _frame_index(series_time: np.ndarray, frames_time: np.ndarray) -> np.ndarray:
    idx = np.searchsorted(series_time, frames_time)
    if np.any(idx >= len(series_time)) or np.any(series_time[np.minimum(idx, len(series_time) - 1)] != frames_time):
        raise PrepError("milan demo assets: a frame timestamp is missing from the shipped series")
    return idx


def fit_profile_mix(frames: np.ndarray, frames_time: np.ndarray, level: np.ndarray, series_time: np.ndarray,
                    a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-square weight m of profile A against B and damping f of the within-day swing, fitted to real frames.

    Least squares per square: for each f on a grid of steps of 0.02 the best m in [0, 1] is closed-form; the
    (f, m) with the smallest squared error wins (ties: the smaller f).

    Args:
        frames: (K, G) real values of the squares at K timestamps.
        frames_time: (K,) timestamps (ms) of the frames; each must be in `series_time`.
        level: (G,) mean value per slot of each square (two-month total / number of slots).
        series_time, a, b: (N,) the two real profiles (whole days), scaled to mean 1.
    Returns:
        (mix, damp), each (G,) in [0, 1]: frames ~ level * profiles(a, b, mix, damp) at the frames' times.
    """
    idx = _frame_index(series_time, frames_time)
    am, bm = day_means(a)[idx], day_means(b)[idx]
    y = frames / level[None, :]
    best = np.full(y.shape[1], np.inf)
    mix, damp = np.zeros(y.shape[1]), np.zeros(y.shape[1])
    for f in _DAMP_GRID:
        pa, pb = (1.0 - f) * a[idx] + f * am, (1.0 - f) * b[idx] + f * bm
        d = pa - pb
        m = np.clip((d[:, None] * (y - pb[:, None])).sum(axis=0) / float(np.dot(d, d)), 0.0, 1.0)
        sse = ((y - pb[:, None] - m[None, :] * d[:, None]) ** 2).sum(axis=0)
        better = sse < best
        best, mix, damp = np.where(better, sse, best), np.where(better, m, mix), np.where(better, f, damp)
    return mix, damp


def _kernel(ell: float) -> np.ndarray:
    """The 1-D Gaussian kernel (std `ell` cells) that `gaussian_filter` applies along each axis."""
    radius = int(_TRUNCATE * ell + 0.5)
    delta = np.zeros(2 * radius + 1)
    delta[radius] = 1.0
    return gaussian_filter1d(delta, ell, mode="constant", truncate=_TRUNCATE) if ell > 0 else delta


def spatial_correlation(ell: float, offsets: tuple[int, ...] = FIT_OFFSETS) -> np.ndarray:
    """Correlation of Gaussian-smoothed white noise (kernel std `ell` cells) between squares `offsets` apart
    along a row or a column, on the grid, as `residual_field` draws it."""
    k = _kernel(ell)
    return np.array([np.dot(k[:len(k) - d], k[d:]) if d < len(k) else 0.0 for d in offsets]) / np.dot(k, k)


def residual_field(rng: np.random.Generator, n: int, rows: int, cols: int, tau: float, ell: float) -> np.ndarray:
    """A unit-variance Gaussian field: white noise smoothed in space (std `ell` cells), AR(1) in time.

    Args:
        rng: random source.
        n: number of slots.
        rows, cols: grid size.
        tau: e-folding time in slots (lag-1 correlation exp(-1/tau)); 0 draws independent slots.
        ell: std of the spatial Gaussian kernel in cells; 0 leaves squares independent.
    Returns:
        (n, rows, cols), stationary: every value N(0, 1), starting from the stationary law.
    """
    k = _kernel(ell)
    r = len(k) // 2
    z = rng.standard_normal((n, rows + 2 * r, cols + 2 * r))
    if ell > 0:  # squares at least r from the padded edge see the whole kernel: variance (sum k^2)^2
        z = gaussian_filter(z, ell, mode="constant", truncate=_TRUNCATE, axes=(1, 2))[:, r:r + rows, r:r + cols]
        z /= float(np.dot(k, k))
    phi = float(np.exp(-1.0 / tau)) if tau > 0 else 0.0
    x = np.empty_like(z)
    x[0] = z[0]
    if n > 1:  # x_t = phi x_{t-1} + sqrt(1 - phi^2) z_t
        x[1:], _ = lfilter([np.sqrt(1.0 - phi ** 2)], [1.0, -phi], z[1:], axis=0, zi=phi * z[:1])
    return x


def fit_persistence(series_time: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    """Persistence (slots) of a square's departures from its usual profile, from the two real 62-day series.

    Each series' log departs from its own mean profile of the same weekday (days 2013-11-01..12-20); the
    difference of the two departures (what moves one square's share against the other's) has covariance
    fitted as nugget + two exponentials, one faster than a day and one slower. The faster one's e-folding time
    is returned: the hours over which a square drifts from its profile and back.

    Args:
        series_time, a, b: (N,) the two real series from local midnight (raw or scaled: only logs are used).
    Returns:
        tau in slots.
    """
    n_days = PERSISTENCE_DAYS
    first = dt.datetime.fromtimestamp((int(series_time[0]) + _LOCAL_OFFSET_MS) / 1000, dt.UTC).date()
    weekday = (first.weekday() + np.arange(n_days)) % 7

    def departure(x: np.ndarray) -> np.ndarray:
        logs = np.log(x[:n_days * _SLOTS]).reshape(n_days, _SLOTS)
        usual = np.stack([logs[weekday == k].mean(axis=0) for k in range(7)])
        return (logs - usual[weekday]).ravel()

    d = departure(a) - departure(b)
    d = d - d.mean()
    lags = np.arange(PERSISTENCE_MAX_LAG + 1)
    cov = np.array([np.mean(d[lag:] * d[:len(d) - lag]) for lag in lags])

    def resid(p: np.ndarray) -> np.ndarray:
        nugget, s1, t1, s2, t2 = np.exp(p)
        return nugget * (lags == 0) + s1 * np.exp(-lags / t1) + s2 * np.exp(-lags / t2) - cov

    lo = np.log([1e-6, 1e-6, 1.0, 1e-6, float(_SLOTS)])
    hi = np.log([1.0, 1.0, float(_SLOTS), 1.0, 1e6])
    fit = least_squares(resid, np.log([0.01, 0.02, 12.0, 0.01, 1000.0]), bounds=(lo, hi))
    return float(np.exp(fit.x[2]))


def _increment_covariance(r: np.ndarray, w: np.ndarray, max_lag: int, offsets: tuple[int, ...]) -> np.ndarray:
    """Weighted covariance of lag-L increments between squares d apart along rows and columns.

    Args:
        r: (K, R, C) consecutive slots; w: (R, C) square weights (a pair weighs sqrt(w_i w_j)).
    Returns:
        (max_lag, len(offsets)) for L = 1..max_lag.
    """
    rows, cols = r.shape[1:]
    out = np.zeros((max_lag, len(offsets)))
    for lag in range(1, max_lag + 1):
        inc = r[lag:] - r[:-lag]
        for j, d in enumerate(offsets):
            pairs = [((slice(None), slice(0, cols - d)), (slice(None), slice(d, cols)))]
            if d:
                pairs.append(((slice(0, rows - d), slice(None)), (slice(d, rows), slice(None))))
            num = den = 0.0
            for p, q in pairs:
                pw = np.sqrt(w[p] * w[q])
                num += float((pw[None] * inc[(slice(None), *p)] * inc[(slice(None), *q)]).sum())
                den += float(pw.sum()) * inc.shape[0]
            out[lag - 1, j] = num / den
    return out


def fit_residual_field(frames: np.ndarray, frames_time: np.ndarray, mean: np.ndarray, level: np.ndarray,
                       tau: float) -> dict[str, float]:
    """Amplitude and spatial scale of the residual field, fitted to the real frames given its persistence.

    Residual = log(frame / model mean), each frame less its demand-weighted mean over the squares (only shares
    matter). Its increments over L slots, at every lag L within each run of consecutive frames, have
    covariances, between squares d = 0..4 apart, weighted by demand (squares with a zero frame left out);
    least squares fits them with two parts: slot-to-slot noise (2 s_e^2 rho_e(d)) and the AR(1) field
    (2 sigma^2 (1 - exp(-L/tau)) rho(d)), rho being `spatial_correlation`. A lag's residuals weigh
    sqrt(number of frame pairs at that lag), so the few pairs at the longest lags count little. Increments
    leave out what stays put over a run (the squares' levels on that day), which the field need not explain.

    Args:
        frames: (K, R, C) real values; frames_time: (K,) their timestamps (ms).
        mean: (K, R, C) the model mean (level x profile) at the same times.
        level: (R, C) the squares' mean level (the weights).
        tau: the field's persistence in slots (`fit_persistence`).
    Returns:
        {"sigma", "smooth_cells"} of the field and {"noise_sigma", "noise_smooth_cells"} of the noise part.
    """
    ok = np.all(frames > 0, axis=0) & np.all(mean > 0, axis=0)
    w = np.where(ok, level, 0.0)
    r = np.log(np.where(ok, frames, 1.0) / np.where(ok, mean, 1.0))
    r = r - (r * w).sum(axis=(1, 2), keepdims=True) / w.sum()
    cuts = np.flatnonzero(np.diff(frames_time) != SLOT_MS) + 1
    emp = [_increment_covariance(run, w, len(run) - 1, FIT_OFFSETS) for run in np.split(r, cuts) if len(run) > 1]

    def resid(p: np.ndarray) -> np.ndarray:
        se, le, sigma, ell = p
        out = []
        for c in emp:
            lags = np.arange(1, len(c) + 1)[:, None]
            model = 2 * se ** 2 * spatial_correlation(le)[None] \
                + 2 * sigma ** 2 * (1 - np.exp(-lags / tau)) * spatial_correlation(ell)[None]
            out.append(((model - c) * np.sqrt(len(c) + 1 - lags)).ravel())  # len(c) + 1 - L pairs at lag L
        return np.concatenate(out)

    fit = least_squares(resid, [0.1, 0.5, 0.3, 1.0], bounds=([0.0, 0.0, 0.0, 0.0], [2.0, 5.0, 2.0, 5.0]))
    se, le, sigma, ell = (float(v) for v in fit.x)
    return {"sigma": sigma, "smooth_cells": ell, "noise_sigma": se, "noise_smooth_cells": le}


def expected_values(cfg: MilanConfig) -> dict[str, np.ndarray]:
    """The demo's mean value of every crop square in every slot of the two shipped months.

    Args:
        cfg: datasets.milan (crop and demo settings).
    Returns:
        dict with time_ms (N,) slot starts (UTC ms), squares (G,) square ids in tensor order (row-major from
        the crop's south-west corner), totals (G,) the real two-month totals, mix and damp (G,) the fitted
        profile weights, and mean (N, G) = level x profile x residual field, whose sum over the N slots is
        each square's real two-month total.
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
    mix, damp = fit_profile_mix(frames.reshape(len(frames), -1), assets["frames_time"], level, t_series, a, b)
    rel = profiles(a, b, mix, damp)  # (N, G)
    if demo.field_sigma > 0:
        x = residual_field(np.random.default_rng([demo.seed, _FIELD_STREAM]), len(t_series), crop.rows, crop.cols,
                           demo.field_tau_slots, demo.field_smooth_cells).reshape(len(t_series), -1)
        moved = rel * np.exp(demo.field_sigma * x)
        rel = moved * (rel.sum(axis=0) / moved.sum(axis=0))  # each square's two-month total stays the real one
    rr, cc = np.meshgrid(np.arange(rs.start, rs.stop), np.arange(cs.start, cs.stop), indexing="ij")
    return {"time_ms": t_series, "squares": (rr * cfg.full_cols + cc + 1).ravel(), "totals": totals, "mix": mix,
            "damp": damp, "mean": level[None, :] * rel}


def generate(cfg: MilanConfig, out_dir: Path) -> list[Path]:
    """Writes one raw daily file per configured day into `out_dir`.

    Args:
        cfg: datasets.milan (crop, split, demo settings).
        out_dir: destination directory (created).
    Returns:
        The written file paths.
    """
    demo = cfg.demo
    model = expected_values(cfg)
    t_series, squares, expected = model["time_ms"], model["squares"], model["mean"]
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for day in tqdm(calendar_days(cfg.split, dataset="milan"), desc="milan demo days", unit="day"):
        midnight_utc = int(dt.datetime.combine(day.key, dt.time(0), tzinfo=dt.UTC).timestamp() * 1000) \
            - _LOCAL_OFFSET_MS
        pos = int(np.searchsorted(t_series, midnight_utc))
        if pos + _SLOTS > len(t_series) or t_series[pos] != midnight_utc:
            raise PrepError(f"datasets.milan.split: the demo has real series for 2013-11-01..2014-01-01 only; "
                            f"found day {day.label}")
        rng = np.random.default_rng([demo.seed, day.key.toordinal()])
        mean = expected[pos:pos + _SLOTS]
        noise = rng.normal(0.0, demo.noise_sigma, mean.shape) - demo.noise_sigma ** 2 / 2
        day_level = rng.normal(0.0, demo.day_level_sigma, (1, mean.shape[1])) - demo.day_level_sigma ** 2 / 2
        values = mean * np.exp(noise + day_level)  # (144, G)
        times = midnight_utc + SLOT_MS * np.arange(_SLOTS, dtype=np.int64)
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
