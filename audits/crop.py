"""Statistics family, part 3: the spatial crop of each dataset.

Milan's crop is fixed by the settings. Shanghai's and YJMob's is the window with the most TRAINING-period records
(docs/PROTOCOL.md §4): the audit counts the raw records per cell of the full grid again (through the `prep`
readers), over the training segment and over all days, finds the densest window with its own code, and
compares both with the crop recorded in meta.json.
"""
from __future__ import annotations

import datetime as dt

import numpy as np
import polars as pl

from audits.context import AuditContext, AuditInputError
from audits.report import Check


def densest(totals: np.ndarray, rows: int, cols: int) -> tuple[int, int, float]:
    """(first_row, first_col, sum) of the rows x cols window with the largest sum; ties: smallest (row, col).

    Args:
        totals: (H, W) per-cell totals.
    """
    c = np.zeros((totals.shape[0] + 1, totals.shape[1] + 1))
    c[1:, 1:] = totals.astype(np.float64).cumsum(0).cumsum(1)
    sums = c[rows:, cols:] - c[:-rows, cols:] - c[rows:, :-cols] + c[:-rows, :-cols]  # (H-rows+1, W-cols+1)
    r, k = np.unravel_index(int(np.argmax(sums)), sums.shape)  # first maximum in row-major order
    return int(r), int(k), float(sums[r, k])


def _yjmob_totals(ctx: AuditContext) -> tuple[np.ndarray, np.ndarray]:
    """(train, all-days) record counts per cell of the full YJMob grid, row = y - 1, col = x - 1."""
    from prep.yjmob import iter_records

    cfg = ctx.section("yjmob")
    n = int(cfg.full_size)
    cal = ctx.calendar("yjmob")
    train = np.array([int(lab[1:]) for lab, s in cal if s == "train"])
    allowed = {int(lab[1:]) for lab, _ in cal}
    tot = {"train": np.zeros(n * n, dtype=np.int64), "all": np.zeros(n * n, dtype=np.int64)}
    for path in ctx.raw_paths("yjmob"):
        for df in iter_records(path, full_size=n, masked_value=cfg.masked_value, n_days=cfg.n_days,
                               raw_slots=cfg.raw_slots_per_day, allowed_days=allowed,
                               on_out_of_range=cfg.on_out_of_range, dropped={}):
            flat = (df["y"].to_numpy().astype(np.int64) - 1) * n + df["x"].to_numpy() - 1
            tot["all"] += np.bincount(flat, minlength=n * n)
            tot["train"] += np.bincount(flat[np.isin(df["d"].to_numpy(), train)], minlength=n * n)
    return tot["train"].reshape(n, n), tot["all"].reshape(n, n)


def _shanghai_totals(ctx: AuditContext) -> tuple[np.ndarray, np.ndarray]:
    """(train, all-days) session starts per cell of the full Shanghai grid (inside the declared box)."""
    from prep.grid import LatLonGrid
    from prep.shanghai import iter_sessions

    cfg = ctx.section("shanghai")
    grid = LatLonGrid(lat_min=cfg.lat_min, lat_max=cfg.lat_max, lon_min=cfg.lon_min, lon_max=cfg.lon_max,
                      cell_m=cfg.cell_m)
    rows, cols = grid.shape
    seg = {s: [dt.date.fromisoformat(v).toordinal() for v in ends] for s, ends in ctx.split_cfg("shanghai").items()}
    tot = {"train": np.zeros(rows * cols, dtype=np.int64), "all": np.zeros(rows * cols, dtype=np.int64)}
    for _, _, s in iter_sessions(ctx.raw_paths("shanghai")):
        lat, lon = s["latitude"].to_numpy(), s["longitude"].to_numpy()
        ordinal = s["start"].dt.date().cast(pl.Int64).to_numpy() + dt.date(1970, 1, 1).toordinal()
        in_train = (ordinal >= seg["train"][0]) & (ordinal <= seg["train"][1])
        in_any = in_train | ((ordinal >= seg["test"][0]) & (ordinal <= seg["test"][1]))
        keep = grid.inside(lat, lon) & in_any
        r, c = grid.cells(lat[keep], lon[keep])
        flat = r * cols + c
        tot["all"] += np.bincount(flat, minlength=rows * cols)
        tot["train"] += np.bincount(flat[in_train[keep]], minlength=rows * cols)
    return tot["train"].reshape(rows, cols), tot["all"].reshape(rows, cols)


def check_crop(ctx: AuditContext) -> Check:
    """The crop is the configured one (Milan) or the densest window of the TRAINING records."""
    chk = Check(id="statistics.crop", family="statistics",
                claim="Each dataset's spatial crop is the configured window (Milan) or the window with the most "
                      "raw TRAINING-period records, recounted from the raw files over the full grid; where the "
                      "all-days window differs, the crop is not that one.")
    for ds in ctx.datasets:
        try:
            meta = ctx.meta(ds)
            crop, where = meta.get("crop", {}), ctx.rel(ctx.meta_path(ds))
            if crop.get("rule") == "fixed":
                want = {k: getattr(ctx.section(ds).crop, k) for k in ("first_row", "first_col", "rows", "cols")}
                got = {k: crop.get(k) for k in want}
                if got != want:
                    chk.fail(f"{where}: crop {got}, config datasets.{ds}.crop is {want}")
                chk.evidence[ds] = {"rule": "fixed", "crop": got}
                continue
            if ds not in ("yjmob", "shanghai"):
                chk.fail(f"{where}: crop rule {crop.get('rule')!r} is not one the audit can recompute")
                continue
            train, alld = _yjmob_totals(ctx) if ds == "yjmob" else _shanghai_totals(ctx)
        except AuditInputError as exc:
            chk.fail(f"{exc} — the crop cannot be verified")
            continue
        h, w = int(crop.get("rows", 0)), int(crop.get("cols", 0))
        r_tr, c_tr, n_tr = densest(train, h, w)
        r_all, c_all, _ = densest(alld, h, w)
        got = (int(crop["first_y"]) - 1, int(crop["first_x"]) - 1) if ds == "yjmob" else \
            (int(crop["first_row"]), int(crop["first_col"]))
        if got != (r_tr, c_tr):
            leak = (" — it is the densest window over ALL days: crop chosen with test-period records"
                    if got == (r_all, c_all) and (r_all, c_all) != (r_tr, c_tr) else "")
            chk.fail(f"{where}: crop starts at (row, col) {got}, the densest {h}x{w} window of the raw training "
                     f"records starts at {(r_tr, c_tr)} ({int(n_tr)} records){leak}")
        chk.evidence[ds] = {"stored": got, "train_window": [r_tr, c_tr], "all_days_window": [r_all, c_all],
                            "train_records_in_window": int(n_tr), "grid": list(train.shape)}
    return chk
