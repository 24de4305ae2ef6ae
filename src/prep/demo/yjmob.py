"""YJMob100K demo: `yjmob100k-dataset1.csv.gz` (uid,d,t,x,y; 999 = masked) for a synthetic city.

Each user has a home, most a workplace near the centre, and a favourite hub (a station: a few cells that
concentrate visits). A user-day has a Poisson number of records (the real 700-user sample: 13.1 per user
and day) at distinct 30-min slots drawn from the real sample's time-of-day shape (night ~0.33 of the mean,
office hours ~1.5). Where a record sits depends on the time of day and on the weekday: on working days
employed users are at work during office hours, on the demo weekend (`weekend_phases`) they stay near home
or go out, so the dense centre carries a weekly cycle. As in the published file, the last days of a share
of users are masked with 999.
"""
from __future__ import annotations

import gzip
import io
from pathlib import Path

import numpy as np
import polars as pl
from tqdm import tqdm

from prep.atomic import atomic_path
from prep.config import YJMobConfig

FILE_NAME = "yjmob100k-dataset1.csv.gz"
# Time-of-day shape of records per 30-min slot (mean 1), piecewise linear through the hourly levels of the
# real 700-user sample: ~0.33 from midnight to 05:00, rising from 06:00 to 1.5 by 08:00, ~1.45 until 19:00,
# then falling to ~0.4 at midnight.
_HOURS = np.array([0, 5, 6, 8, 12, 16, 19, 22, 24], dtype=float)
_LEVEL = np.array([0.36, 0.32, 0.45, 1.45, 1.55, 1.45, 1.35, 0.8, 0.36])
EMPLOYED_FRAC = 0.7  # share of users with a workplace (the rest: home-centred days)


def slot_profile(raw_slots: int = 48) -> np.ndarray:
    """(raw_slots,) probability of a record falling in each 30-min slot."""
    mid = (np.arange(raw_slots) + 0.5) * 24.0 / raw_slots
    p = np.interp(mid, _HOURS, _LEVEL)
    return p / p.sum()


def _clip_cells(v: np.ndarray, n: int) -> np.ndarray:
    return np.clip(np.rint(v), 1, n).astype(np.int16)


def generate(cfg: YJMobConfig, out_dir: Path) -> list[Path]:
    """Writes the demo `yjmob100k-dataset1.csv.gz` into `out_dir`; returns [path]."""
    demo, n, T = cfg.demo, cfg.full_size, cfg.raw_slots_per_day
    rng = np.random.default_rng(demo.seed)
    cx, cy = demo.centre_xy
    u = demo.n_users
    home = np.stack([_clip_cells(cx + rng.normal(0, demo.home_sigma_cells, u), n),
                     _clip_cells(cy + rng.normal(0, demo.home_sigma_cells, u), n)], axis=1)
    hubs = np.stack([_clip_cells(cx + rng.normal(0, demo.work_sigma_cells, demo.n_hubs), n),
                     _clip_cells(cy + rng.normal(0, demo.work_sigma_cells, demo.n_hubs), n)], axis=1)
    work_at_hub = rng.random(u) < demo.hub_share
    fav_hub = rng.integers(0, demo.n_hubs, u)
    work = np.where(work_at_hub[:, None], hubs[fav_hub],
                    np.stack([_clip_cells(cx + rng.normal(0, demo.work_sigma_cells, u), n),
                              _clip_cells(cy + rng.normal(0, demo.work_sigma_cells, u), n)], axis=1))
    employed = rng.random(u) < EMPLOYED_FRAC
    masked_user = np.arange(u) >= int(round(u * (1 - demo.masked_user_frac)))
    p_slot = np.log(slot_profile(T))
    hour = (np.arange(T) + 0.5) * 24.0 / T
    # Personal schedules (hours): office from ~9 to ~18, out of home from ~7 to ~21, each with a spread.
    work_from, work_to = rng.normal(8.75, 0.75, u), rng.normal(18.0, 1.0, u)
    out_from, out_to = rng.normal(7.0, 1.0, u), rng.normal(21.5, 1.25, u)
    parts = []
    for d in tqdm(range(cfg.n_days), desc="yjmob demo days", unit="day"):
        weekend = bool((d % 7) in demo.weekend_phases)
        k = np.clip(rng.poisson(demo.records_per_user_day * (0.9 if weekend else 1.0), u), 1, T)
        keys = p_slot[None, :] + rng.gumbel(size=(u, T))  # Gumbel top-k = sampling slots without replacement
        order = np.argsort(-keys, axis=1)
        take = np.arange(T)[None, :] < k[:, None]
        user = np.repeat(np.arange(u), k)
        t = np.sort(np.where(take, order, T), axis=1)
        t = t[t < T]
        # Where each record is: home, work, hub or elsewhere (errands / leisure around the centre).
        r = rng.random(user.size)
        h = hour[t]
        office = (h >= work_from[user]) & (h < work_to[user])
        night = (h < out_from[user]) | (h >= out_to[user])
        at_work = employed[user] & office & (r < 0.75) & (not weekend)
        at_hub = ~at_work & ~night & (r > 0.75) & (r < 0.75 + demo.hub_visit_frac * (2 if weekend else 1))
        at_home = ~at_work & ~at_hub & (night | (rng.random(user.size) < 0.5))
        x = np.where(at_home, home[user, 0], 0).astype(np.int16)
        y = np.where(at_home, home[user, 1], 0).astype(np.int16)
        x = np.where(at_work, work[user, 0], x)
        y = np.where(at_work, work[user, 1], y)
        x = np.where(at_hub, hubs[fav_hub[user], 0], x)
        y = np.where(at_hub, hubs[fav_hub[user], 1], y)
        other = ~(at_home | at_work | at_hub)
        ox = np.where(weekend, cx, home[user, 0]) + rng.normal(0, demo.home_sigma_cells / 2, user.size)
        oy = np.where(weekend, cy, home[user, 1]) + rng.normal(0, demo.home_sigma_cells / 2, user.size)
        x = np.where(other, _clip_cells(ox, n), x)
        y = np.where(other, _clip_cells(oy, n), y)
        if d >= demo.masked_first_day:
            m = masked_user[user]
            x = np.where(m, cfg.masked_value, x).astype(np.int16)
            y = np.where(m, cfg.masked_value, y).astype(np.int16)
        parts.append(pl.DataFrame({"uid": user.astype(np.int32), "d": np.full(user.size, d, np.int16),
                                   "t": t.astype(np.int16), "x": x, "y": y}))
    table = pl.concat(parts).sort("uid", "d", "t")
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / FILE_NAME
    buf = io.BytesIO()
    table.write_csv(buf)
    with atomic_path(path) as tmp, open(tmp, "wb") as raw, \
            gzip.GzipFile(filename="", mode="wb", fileobj=raw, mtime=0, compresslevel=6) as gz:
        gz.write(buf.getvalue())
    return [path]
