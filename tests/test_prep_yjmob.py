"""YJMob reader and tensor on the real 700-user sample; week recovery; demo against the real sample."""
from __future__ import annotations

import dataclasses
import gzip
from collections import defaultdict
from pathlib import Path

import numpy as np
import polars as pl
import yaml

from prep import stats, yjmob
from prep.config import datasets_config
from prep.demo.yjmob import generate, slot_profile
from prep.grid import densest_window

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT.parent / "shared" / "data" / "real" / "yjmob100k" / "yjmob100k_dataset1_annizheng_700users.csv"


def _config(**split):
    cfg = datasets_config(yaml.safe_load((ROOT / "config.yaml").read_text())["datasets"]).yjmob
    if split:
        cfg = dataclasses.replace(cfg, split=dataclasses.replace(cfg.split, **split))
    return cfg


def _sample_rows() -> list[tuple[int, int, int, int, int]]:
    lines = SAMPLE.read_text().splitlines()
    assert lines[0].split(",")[:5] == ["uid", "d", "t", "x", "y"]
    return [tuple(int(v) for v in ln.split(",")[:5]) for ln in lines[1:]]


def test_real_sample_distinct_users_per_cell_equal_a_direct_count():
    rows = _sample_rows()
    users = defaultdict(set)
    for uid, d, t, x, y in rows:
        users[(d, t, x, y)].add(uid)
    got = yjmob.distinct_counts(yjmob.read_raw(SAMPLE))  # the sample carries an extra column: ignored
    assert got.height == len(users)
    for d, t, x, y, n in got.iter_rows():
        assert n == len(users[(d, t, x, y)])


def test_real_sample_tensor_deaggregates_back_to_30min_counts_in_the_densest_window():
    # The sample covers days 0..33: train 0..20, test 21..33.
    cfg = _config(train=("0", "20"), test=("21", "33"))
    raw = yjmob.build(cfg, [SAMPLE])
    rows = _sample_rows()
    grid = np.zeros((200, 200))
    for uid, d, t, x, y in rows:
        if d <= 20:
            grid[y - 1, x - 1] += 1
    r0, c0, _ = densest_window(grid, 9, 9)
    assert (raw.crop["first_y"], raw.crop["first_x"]) == (r0 + 1, c0 + 1)
    users = defaultdict(set)
    for uid, d, t, x, y in rows:
        if r0 + 1 <= y <= r0 + 9 and c0 + 1 <= x <= c0 + 9:
            users[(d, t, y - r0 - 1, x - c0 - 1)].add(uid)
    counts30 = np.zeros((34, 48, 9, 9))
    for (d, t, r, c), s in users.items():
        counts30[d, t, r, c] = len(s)
    ten = raw.values  # (34, 144, 9, 9)
    assert ten.shape == (34, 144, 9, 9)
    assert np.allclose(ten.reshape(34, 48, 3, 9, 9).sum(axis=2), counts30, rtol=0, atol=1e-12)
    assert np.allclose(ten[:, 0::3], ten[:, 1::3]) and np.allclose(ten[:, 0::3], ten[:, 2::3])


def test_masked_rows_are_dropped_with_a_count_and_gz_is_read(tmp_path):
    text = "uid,d,t,x,y\n1,0,0,5,5\n1,0,1,999,999\n2,0,1,5,5\n2,0,1,5,5\n3,1,0,6,5\n3,1,2,999,999\n"
    path = tmp_path / "yjmob100k-dataset1.csv.gz"
    path.write_bytes(gzip.compress(text.encode()))
    dropped = {}
    df = yjmob.read_raw(path, dropped=dropped)
    assert dropped["masked_999"] == 2 and df.height == 4
    counts = yjmob.distinct_counts(df.unique()).sort("d", "t", "x")
    assert counts.rows() == [(0, 0, 5, 5, 1), (0, 1, 5, 5, 1), (1, 0, 6, 5, 1)]


def test_week_recovery_finds_lag_7_and_the_two_quiet_phases():
    from prep.config import WeekRecovery
    from prep.days import recover_week

    d = np.arange(56)
    level = np.array([10.0, 10.5, 9.8, 10.2, 10.1, 6.0, 5.0])  # phases 5 and 6 quiet
    totals = level[d % 7] + np.random.default_rng(0).normal(0, 0.2, d.size)
    week = recover_week(d, totals, WeekRecovery(min_lag=2, max_lag=14, n_weekend_phases=2))
    assert week.lag == 7 and week.pseudo_weekend_phases == [5, 6]
    # Shifted start: day numbers 3..58 keep the phases of d mod 7.
    week2 = recover_week(d + 3, level[(d + 3) % 7], WeekRecovery(min_lag=2, max_lag=14, n_weekend_phases=2))
    assert week2.lag == 7 and week2.pseudo_weekend_phases == [5, 6]


def test_demo_matches_real_sample_and_spec_statistics(tmp_path):
    cfg = _config()  # the configured demo, as the pipeline generates it
    files = generate(cfg, tmp_path)
    assert files[0].name == "yjmob100k-dataset1.csv.gz"
    assert gzip.decompress(files[0].read_bytes()).startswith(b"uid,d,t,x,y\n")
    demo = pl.read_csv(files[0])
    real = pl.read_csv(SAMPLE)
    masked = demo.filter(pl.col("x") == 999)
    assert masked.height > 0 and masked["d"].min() == cfg.demo.masked_first_day
    demo = demo.filter(pl.col("x") != 999)
    # Records per user and day (real sample: 13.1).
    per_ud = lambda df: df.group_by("uid", "d").len()["len"].mean()  # noqa: E731
    assert abs(per_ud(demo) - per_ud(real)) < 1.5
    # Time-of-day shape of records per 30-min slot.
    prof = lambda df: df.group_by("t").len().sort("t")["len"].to_numpy() / df.height  # noqa: E731
    assert np.corrcoef(prof(demo), prof(real))[0, 1] > 0.95
    assert np.corrcoef(slot_profile(48), prof(real))[0, 1] > 0.95
    raw = yjmob.build(cfg, files)
    assert raw.week["lag"] == 7 and raw.week["pseudo_weekend_phases"] == sorted(cfg.demo.weekend_phases)
    assert abs(stats.top_share(raw.values, 0.05) - 0.22) < 0.04  # docs/PROTOCOL.md §4: top 5% of cells carry ~22%
    assert raw.dropped["masked_999"] == masked.height


def test_demo_is_deterministic_and_seed_dependent(tmp_path):
    cfg = _config()
    small = dataclasses.replace(cfg, demo=dataclasses.replace(cfg.demo, n_users=200))
    a = generate(small, tmp_path / "a")[0].read_bytes()
    b = generate(small, tmp_path / "b")[0].read_bytes()
    c = generate(dataclasses.replace(small, demo=dataclasses.replace(small.demo, seed=small.demo.seed + 1)),
                 tmp_path / "c")[0].read_bytes()
    assert a == b and a != c
