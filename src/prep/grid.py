"""Gridding helpers: densest-window search and latitude/longitude to cell indices."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

EARTH_RADIUS_M = 6_371_008.8  # mean Earth radius (IUGG)


def densest_window(totals: np.ndarray, rows: int, cols: int) -> tuple[int, int, float]:
    """The rows x cols window with the largest sum.

    Args:
        totals: (H, W) per-cell totals (e.g. training-period counts), row 0 = south.
        rows, cols: window size.
    Returns:
        (first_row, first_col, window_sum); ties go to the smallest (row, col).
    Raises:
        ValueError: the window does not fit the grid.
    """
    h, w = totals.shape
    if not (0 < rows <= h and 0 < cols <= w):
        raise ValueError(f"window {rows}x{cols} does not fit a {h}x{w} grid")
    c = np.zeros((h + 1, w + 1), dtype=np.float64)
    c[1:, 1:] = np.cumsum(np.cumsum(totals.astype(np.float64), axis=0), axis=1)
    sums = c[rows:, cols:] - c[:-rows, cols:] - c[rows:, :-cols] + c[:-rows, :-cols]
    r, k = np.unravel_index(int(np.argmax(sums)), sums.shape)
    return int(r), int(k), float(sums[r, k])


@dataclass(frozen=True, kw_only=True)
class LatLonGrid:
    """Square cells of `cell_m` metres over a latitude/longitude box, row 0 at lat_min, col 0 at lon_min.

    Projection: local equirectangular about the box's mid-latitude (error < 0.1% over a city-sized box).
    """

    lat_min: float
    lat_max: float
    lon_min: float
    lon_max: float
    cell_m: float

    @property
    def _m_per_deg_lat(self) -> float:
        return EARTH_RADIUS_M * math.pi / 180.0

    @property
    def _m_per_deg_lon(self) -> float:
        return self._m_per_deg_lat * math.cos(math.radians((self.lat_min + self.lat_max) / 2))

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols) of the full grid covering the box."""
        rows = math.ceil((self.lat_max - self.lat_min) * self._m_per_deg_lat / self.cell_m)
        cols = math.ceil((self.lon_max - self.lon_min) * self._m_per_deg_lon / self.cell_m)
        return rows, cols

    def inside(self, lat: np.ndarray, lon: np.ndarray) -> np.ndarray:
        """Boolean mask of points inside the box (bounds included)."""
        return (lat >= self.lat_min) & (lat <= self.lat_max) & (lon >= self.lon_min) & (lon <= self.lon_max)

    def cells(self, lat: np.ndarray, lon: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(row, col) int64 arrays of points inside the box (the max bound falls in the last cell)."""
        rows, cols = self.shape
        r = np.floor((lat - self.lat_min) * self._m_per_deg_lat / self.cell_m).astype(np.int64)
        c = np.floor((lon - self.lon_min) * self._m_per_deg_lon / self.cell_m).astype(np.int64)
        return np.minimum(r, rows - 1), np.minimum(c, cols - 1)

    def centre(self, row: np.ndarray, col: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(lat, lon) of cell centres."""
        lat = self.lat_min + (np.asarray(row) + 0.5) * self.cell_m / self._m_per_deg_lat
        lon = self.lon_min + (np.asarray(col) + 0.5) * self.cell_m / self._m_per_deg_lon
        return lat, lon
