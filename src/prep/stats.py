"""Statistics of a demand tensor: training percentile, kappa, zero-cell rate, top-cell share, cycles.

All functions take a dense tensor `values` of shape (days, slots, rows, cols).
"""
from __future__ import annotations

import numpy as np


def percentile(values: np.ndarray, day_idx: np.ndarray, q: float) -> float:
    """q-th percentile (linear interpolation) of the cell-slot values of the given days.

    Args:
        values: (D, T, R, C) demand.
        day_idx: tensor day indices to include (the training days for normalization).
        q: percentile in [0, 100].
    Returns:
        The percentile as a float.
    """
    return float(np.percentile(values[np.asarray(day_idx)].astype(np.float64).ravel(), q))


def mean_of(values: np.ndarray, day_idx: np.ndarray) -> float:
    """Mean cell-slot value over the given days (float64 accumulation)."""
    return float(values[np.asarray(day_idx)].astype(np.float64).mean())


def zero_cell_rate(values: np.ndarray) -> float:
    """Fraction of cell-slot values that are exactly zero, over all days."""
    return float(np.mean(values == 0))


def top_share(values: np.ndarray, frac: float) -> float:
    """Share of total demand carried by the top `frac` of cells, cells ranked by their total over all days.

    The number of top cells is max(1, round(frac * cells)): 20 of 400 for Milan, 4 of 81 for YJMob.
    """
    totals = values.astype(np.float64).sum(axis=(0, 1)).ravel()
    k = max(1, int(round(frac * totals.size)))
    s = float(totals.sum())
    return float(np.sort(totals)[::-1][:k].sum() / s) if s > 0 else 0.0


def daily_totals(values: np.ndarray) -> np.ndarray:
    """(D,) total demand per day."""
    return values.astype(np.float64).sum(axis=(1, 2, 3))


def daily_cycle(values: np.ndarray, day_mask: np.ndarray) -> np.ndarray:
    """(T,) mean crop total per slot over the selected days (zeros if none)."""
    if not np.any(day_mask):
        return np.zeros(values.shape[1])
    return values[np.asarray(day_mask)].astype(np.float64).sum(axis=(2, 3)).mean(axis=0)


def hotspot_motion(values: np.ndarray, frac: float, hours: tuple[int, int] = (4, 14)) -> float:
    """Mean overlap (0..1) of the top-`frac` cell sets of the mean maps at two hours of the day.

    1 means the hotspots stay put; lower values mean the demand map moves through the day.
    """
    per_hour = values.shape[1] // 24
    maps = values.astype(np.float64).mean(axis=0)  # (T, R, C)
    a = maps[hours[0] * per_hour: (hours[0] + 1) * per_hour].mean(axis=0).ravel()
    b = maps[hours[1] * per_hour: (hours[1] + 1) * per_hour].mean(axis=0).ravel()
    k = max(1, int(round(frac * a.size)))
    top_a = set(np.argsort(-a, kind="stable")[:k].tolist())
    top_b = set(np.argsort(-b, kind="stable")[:k].tolist())
    return len(top_a & top_b) / k
