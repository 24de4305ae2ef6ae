"""Statistics of a demand tensor: training percentile, kappa, zero-cell rate, top-cell share, cycles, hotspot
migration.

The tensor functions take a dense tensor `values` of shape (days, slots, rows, cols); the hotspot-migration
functions take consecutive frames (slots, ...) of one window.
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


def top_share_overlap(frames: np.ndarray, k: int, lag: int) -> float | None:
    """Mean overlap (0..1) of the top-k cells of demand-share maps `lag` slots apart.

    A frame's share map is each cell's demand / the frame's total; its top-k set holds the k cells of largest
    share (ties broken by cell index), cells without demand left out. The overlap of a pair of frames t and
    t + lag is |top_k(t) & top_k(t + lag)| / k; the mean runs over every such pair in `frames`.

    Args:
        frames: (T, ...) consecutive slots; the trailing axes are the cells.
        k: cells per top set (>= 1).
        lag: slots between the two frames of a pair (>= 1).
    Returns:
        The mean overlap (1 = the hotspots stay put), or None when no pair has demand in both frames.
    """
    x = frames.reshape(len(frames), -1).astype(np.float64)
    totals = x.sum(axis=1)
    tops = []
    for row, total in zip(x, totals):
        if total > 0:
            order = np.argsort(-(row / total), kind="stable")[:k]
            tops.append(set(order[row[order] > 0].tolist()))
        else:
            tops.append(None)
    pairs = [len(tops[t] & tops[t + lag]) / k for t in range(len(x) - lag)
             if tops[t] is not None and tops[t + lag] is not None]
    return float(np.mean(pairs)) if pairs else None


def energy_outside_first_component(frames: np.ndarray) -> float | None:
    """Share of the demand energy outside the first singular component of the (frames x cells) matrix.

    1 - s_1^2 / sum_i s_i^2 of the raw (uncentred) demand: 0 when every frame is a multiple of one map, larger
    the more the map changes shape across the frames.

    Args:
        frames: (T, ...) slots; the trailing axes are the cells.
    Returns:
        The share in [0, 1], or None when the frames hold no demand.
    """
    x = frames.reshape(len(frames), -1).astype(np.float64)
    s2 = np.linalg.svd(x, compute_uv=False) ** 2
    total = float(s2.sum())
    return float(1.0 - s2[0] / total) if total > 0 else None


def hotspot_migration(frames: np.ndarray, k: int, lag: int) -> dict[str, float | None]:
    """Both hotspot-migration figures of consecutive frames (T, ...): `top_k_share_overlap`
    (`top_share_overlap`) and `energy_outside_first_component`."""
    return {"top_k_share_overlap": top_share_overlap(frames, k, lag),
            "energy_outside_first_component": energy_outside_first_component(frames)}
