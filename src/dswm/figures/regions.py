"""The data of the qualitative figures (``dswm.figures.qualitative``): the Milano GRID and its real per-square totals,
the full regions of Shanghai and YJMob100K read from the raw files, where the prepared crop lies in them, and a day's
busy slot and weekday/weekend mean maps.

Maps are in the tensor's normalized demand units; tensor row 0 is the southern row.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import polars as pl

ASSETS = Path(__file__).resolve().parents[2] / "prep" / "assets" / "milan"
MILAN_GRID = ASSETS / "milano-grid.geojson"
"""The official Milano GRID (EPSG:4326, 10,000 squares, property ``cellId``), copied from the shared data folder."""
MILAN_TOTALS = ASSETS / "square_totals_2mo.csv"
"""Real internet totals per square, 2013-11-01..2014-01-01 (``square_id,internet``)."""


def busy_slot(maps: np.ndarray) -> int:
    """The slot 1..T-1 of ``maps`` (T, R, C) with the largest total demand."""
    totals = np.asarray(maps, dtype=np.float64).reshape(maps.shape[0], -1).sum(1)
    return 1 + int(np.argmax(totals[1:]))


def read_milan_grid(path: str | Path = MILAN_GRID) -> tuple[np.ndarray, np.ndarray]:
    """The Milano GRID: (cellId (N,) int64, outer ring (N, V, 2) lon/lat of every square, closing vertex dropped).

    Raises:
        ValueError: the file is not a FeatureCollection of polygons with a ``cellId`` property.
    """
    data = json.loads(Path(path).read_text())
    try:
        feats = data["features"]
        ids = np.array([int(f["properties"]["cellId"]) for f in feats], dtype=np.int64)
        rings = np.array([f["geometry"]["coordinates"][0][:-1] for f in feats], dtype=np.float64)
    except (KeyError, TypeError, IndexError, ValueError) as exc:
        raise ValueError(f"{path}: expected a GeoJSON FeatureCollection of square polygons with property cellId "
                         f"({exc!r})") from exc
    order = np.argsort(ids)
    return ids[order], rings[order]


def milan_crop_squares(grid: Mapping) -> np.ndarray:
    """(rows, cols) square ids of the crop, tensor orientation (row 0 south), from meta.json ``grid``."""
    r, c = np.meshgrid(np.arange(grid["rows"]), np.arange(grid["cols"]), indexing="ij")
    return (grid["first_row"] + r) * grid["full_cols"] + grid["first_col"] + c + 1


def milan_crop_outline(ids: np.ndarray, rings: np.ndarray, grid: Mapping) -> np.ndarray:
    """(4, 2) lon/lat corners SW, SE, NE, NW of the crop on the Milano GRID (from its four corner squares)."""
    squares = milan_crop_squares(grid)
    where = {int(i): k for k, i in enumerate(ids)}

    def ring(square: int) -> np.ndarray:
        if int(square) not in where:
            raise ValueError(f"Milano GRID: no square {int(square)} (the crop of meta.json grid {dict(grid)})")
        return rings[where[int(square)]]

    sw, se, ne, nw = (ring(squares[0, 0]), ring(squares[0, -1]), ring(squares[-1, -1]), ring(squares[-1, 0]))
    return np.array([[sw[:, 0].min(), sw[:, 1].min()], [se[:, 0].max(), se[:, 1].min()],
                     [ne[:, 0].max(), ne[:, 1].max()], [nw[:, 0].min(), nw[:, 1].max()]])


def read_milan_totals(path: str | Path = MILAN_TOTALS) -> pl.DataFrame:
    """The real two-month totals per square (square_id Int64, internet Float64)."""
    return pl.read_csv(path, schema_overrides={"square_id": pl.Int64, "internet": pl.Float64})


def shanghai_region(cfg, paths: Sequence[str | Path]) -> np.ndarray:
    """(full_rows, full_cols) session starts per cell of the full grid over the TRAINING days (the totals the crop
    is the densest window of), read with the project's Shanghai reader (``prep.shanghai.iter_sessions``)."""
    from prep.days import configured_days
    from prep.grid import LatLonGrid
    from prep.shanghai import iter_sessions

    grid = LatLonGrid(lat_min=cfg.lat_min, lat_max=cfg.lat_max, lon_min=cfg.lon_min, lon_max=cfg.lon_max,
                      cell_m=cfg.cell_m)
    train = pl.Series([d.key for d in configured_days(cfg, "shanghai") if d.split == "train"], dtype=pl.Date)
    totals = np.zeros(grid.shape, dtype=np.float64)
    for _, _, sessions in iter_sessions([Path(p) for p in paths]):
        lat, lon = sessions["latitude"].to_numpy(), sessions["longitude"].to_numpy()
        keep = grid.inside(lat, lon) & sessions["start"].dt.date().is_in(train.implode()).to_numpy()
        r, c = grid.cells(lat[keep], lon[keep])
        np.add.at(totals, (r, c), 1.0)
    return totals


def yjmob_region(cfg, paths: Sequence[str | Path]) -> np.ndarray:
    """(full_size, full_size) records per cell (row y - 1, column x - 1) over the TRAINING days, masked records
    dropped (the totals the crop is the densest window of), read with ``prep.yjmob.iter_records``."""
    from prep.days import configured_days
    from prep.yjmob import iter_records

    if len(paths) != 1:
        raise ValueError(f"yjmob: expected exactly one raw file, found {len(paths)}: {[str(p) for p in paths]}")
    days = configured_days(cfg, "yjmob")
    train = sorted(int(d.key) for d in days if d.split == "train")
    n = cfg.full_size
    totals = np.zeros(n * n, dtype=np.float64)
    for df in iter_records(paths[0], full_size=n, masked_value=cfg.masked_value, n_days=cfg.n_days,
                           raw_slots=cfg.raw_slots_per_day, allowed_days={int(d.key) for d in days},
                           on_out_of_range=cfg.on_out_of_range):
        tr = np.isin(df["d"].to_numpy(), train)
        flat = (df["y"].to_numpy()[tr].astype(np.int64) - 1) * n + df["x"].to_numpy()[tr].astype(np.int64) - 1
        totals += np.bincount(flat, minlength=n * n)
    return totals.reshape(n, n)


def crop_origin(meta: Mapping) -> tuple[int, int]:
    """(first row, first column) of the crop on the dataset's full grid (YJMob: y - 1, x - 1)."""
    crop = meta["crop"]
    if "first_x" in crop:
        return int(crop["first_y"]) - 1, int(crop["first_x"]) - 1
    return int(crop["first_row"]), int(crop["first_col"])


def check_region(region: np.ndarray, meta: Mapping) -> None:
    """The crop of meta.json is the densest window of ``region`` (the region is the one the crop was cut from).

    Raises:
        ValueError: it is not (raw files changed since the tensor was prepared, or another region was read).
    """
    from prep.grid import densest_window

    rows, cols = meta["grid"]["rows"], meta["grid"]["cols"]
    found = densest_window(region, rows, cols)[:2]
    if found != crop_origin(meta):
        raise ValueError(f"{meta['dataset']}: the densest {rows}x{cols} window of the full region read from the raw "
                         f"files starts at (row, col) {found}, meta.json's crop at {crop_origin(meta)}; expected the "
                         f"same (re-run the prepare rule on these raw files)")


def day_profiles(demand: np.ndarray, meta: Mapping) -> tuple[np.ndarray, np.ndarray, int, int]:
    """(weekday mean map, weekend mean map, weekday count, weekend count) over every day of the tensor.

    Raises:
        ValueError: the tensor has no weekday or no weekend day.
    """
    weekend = np.array([bool(d["weekend"]) for d in meta["days"]])
    if weekend.all() or not weekend.any():
        raise ValueError(f"{meta['dataset']}: meta.json days hold {int(weekend.sum())} weekend days of "
                         f"{len(weekend)}; expected both weekdays and weekend days")
    return (demand[~weekend].mean(axis=(0, 1)), demand[weekend].mean(axis=(0, 1)), int((~weekend).sum()),
            int(weekend.sum()))
