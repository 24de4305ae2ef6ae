"""Shanghai reader (xlsx and CSV), dirt handling, gridding, trailing window, eval days, demo statistics."""
from __future__ import annotations

import dataclasses
import datetime as dt
import math
from pathlib import Path

import numpy as np
import polars as pl
import pytest
import yaml

from prep import shanghai, stats
from prep.config import datasets_config
from prep.days import calendar_days, pick_eval_days
from prep.demo.shanghai import _write_xlsx, add_dirt, generate, half_months, simulate
from prep.grid import LatLonGrid, densest_window

ROOT = Path(__file__).resolve().parents[1]


def _config(train=("2014-06-01", "2014-06-14"), test=("2014-06-15", "2014-06-21")):
    cfg = datasets_config(yaml.safe_load((ROOT / "config.yaml").read_text())["datasets"]).shanghai
    return dataclasses.replace(cfg, split=dataclasses.replace(cfg.split, train=train, test=test))


def _table(rows):
    return pl.DataFrame(rows, schema=["month", "date", "start time", "end time", "latitude", "longitude", "user id"],
                        orient="row")


ROWS = [
    (201406, 20140601, "2014-06-01 08:00:05", "2014-06-01 08:20:00", 31.2304, 121.4737, "a"),
    (201406, 20140601, "2014-06-01 23:55:00", "2014-06-02 00:10:00", 31.2304, 121.4737, "b"),  # crosses midnight
    (201406, 20140601, "2014-06-01 09:00:00", "2014-06-01 08:00:00", 31.2304, 121.4737, "c"),  # end before start
    (201406, 20140601, "2014-06-01 09:10:00", "2014-06-01 09:20:00", None, None, "d"),  # missing location
    (201406, 20140601, "2014-06-01 09:10:00", "2014-06-01 09:20:00", 0.0, 0.0, "e"),  # 0/0
    (201406, 20140602, "2014-06-02 00:09:59", "2014-06-02 00:30:00", 31.2304, 121.4737, "f"),
]


def test_xlsx_and_csv_give_the_same_cleaned_sessions_with_counts(tmp_path):
    table = _table(ROWS)
    xlsx, csv = tmp_path / "data_6.1~6.15.xlsx", tmp_path / "export.csv"
    _write_xlsx(xlsx, table)
    table.write_csv(csv)
    results = []
    for path in (xlsx, csv):
        dropped, notes = {}, {}
        got = shanghai.read_raw([path], dropped=dropped, notes=notes)
        assert dropped == {"missing_location": 1, "zero_location": 1, "end_before_start": 1, "duplicate_rows": 0}
        assert notes == {"crossing_midnight": 1}
        results.append(got)
    a, b = results
    assert a["user_id"].to_list() == ["a", "b", "f"] == b["user_id"].to_list()
    assert a["start"].to_list() == b["start"].to_list() == [dt.datetime(2014, 6, 1, 8, 0, 5),
                                                           dt.datetime(2014, 6, 1, 23, 55),
                                                           dt.datetime(2014, 6, 2, 0, 9, 59)]


def test_gridding_470m_and_trailing_3_slot_window(tmp_path):
    cfg = _config(train=("2014-06-01", "2014-06-01"), test=("2014-06-02", "2014-06-02"))
    cfg = dataclasses.replace(cfg, crop=dataclasses.replace(cfg.crop, rows=2, cols=2))
    grid = LatLonGrid(lat_min=cfg.lat_min, lat_max=cfg.lat_max, lon_min=cfg.lon_min, lon_max=cfg.lon_max,
                      cell_m=470.0)
    # A point 1,000 m north of the box's south edge lies in row 2 (470 m cells: 940..1410 m).
    m_per_deg = 6_371_008.8 * math.pi / 180
    r, c = grid.cells(np.array([cfg.lat_min + 1000 / m_per_deg]), np.array([cfg.lon_min]))
    assert (int(r[0]), int(c[0])) == (2, 0)
    path = tmp_path / "data_6.1~6.15.xlsx"
    _write_xlsx(path, _table(ROWS))
    raw = shanghai.build(cfg, [path])
    # Starts in the window cell: 08:00:05 (day 0 slot 48), 23:55 (day 0 slot 143), 00:09:59 (day 1 slot 0).
    rr, cc = grid.cells(np.array([31.2304]), np.array([121.4737]))
    r0, c0 = raw.crop["first_row"], raw.crop["first_col"]
    assert (r0 <= rr[0] <= r0 + 1) and (c0 <= cc[0] <= c0 + 1)
    v = raw.values[:, :, rr[0] - r0, cc[0] - c0]
    assert v[0, 48] == pytest.approx(1 / 3) and v[0, 49] == pytest.approx(1 / 3) and v[0, 50] == pytest.approx(1 / 3)
    assert v[0, 51] == 0 and v[0, 47] == 0
    assert v[0, 143] == pytest.approx(1 / 3)
    # The window crosses midnight: day 1 slot 0 = (23:50 slot + its own start) / 3, slot 1 the same.
    assert v[1, 0] == pytest.approx(2 / 3) and v[1, 1] == pytest.approx(2 / 3) and v[1, 2] == pytest.approx(1 / 3)
    assert v[1, 3] == 0 and raw.values.sum() == pytest.approx(3.0)
    # The very first slot of the data has no earlier slots: its mean is over the available one.
    assert shanghai.trailing_mean(np.ones((1, 4, 1, 1)), 3, [dt.date(2014, 6, 1)]).ravel().tolist() == [1, 1, 1, 1]


def test_densest_window_matches_brute_force():
    rng = np.random.default_rng(0)
    totals = rng.poisson(2.0, (30, 25)).astype(float)
    best = max(((totals[r:r + 7, c:c + 5].sum(), -r, -c) for r in range(24) for c in range(21)))
    assert densest_window(totals, 7, 5) == (-best[1], -best[2], best[0])


def test_eval_days_for_november_2014():
    cfg = _config(train=("2014-06-01", "2014-10-31"), test=("2014-11-01", "2014-11-30"))
    days = calendar_days(cfg.split, dataset="shanghai")
    picked = pick_eval_days(days, [d.key.weekday() >= 5 for d in days], cfg.eval_days, dataset="shanghai")
    label = {d.index: d.label for d in days}
    # 2014-11-01 is a Saturday.
    assert [label[i] for i in picked["id"]] == ["2014-11-03", "2014-11-04", "2014-11-05"]
    assert [label[i] for i in picked["ood"]] == ["2014-11-01", "2014-11-02", "2014-11-08", "2014-11-09"]


def test_half_month_file_names():
    got = [(a.isoformat(), b.isoformat()) for a, b in half_months(dt.date(2014, 6, 1), dt.date(2014, 7, 31))]
    assert got == [("2014-06-01", "2014-06-15"), ("2014-06-16", "2014-06-30"), ("2014-07-01", "2014-07-15"),
                   ("2014-07-16", "2014-07-31")]


def test_demo_dirt_is_counted_and_zero_cells_near_85_percent(tmp_path):
    cfg = _config()
    sessions = add_dirt(simulate(cfg), cfg)
    files = generate(cfg, tmp_path)
    assert [f.name for f in files] == ["data_6.1~6.15.xlsx", "data_6.16~6.30.xlsx"]
    again = generate(cfg, tmp_path / "again")
    assert [f.read_bytes() for f in files] == [f.read_bytes() for f in again]  # same seed, same bytes
    raw = shanghai.build(cfg, files)
    n_missing = sessions["latitude"].is_null().sum()
    n_zero = (sessions["latitude"] == 0).sum()
    n_rev = (sessions["end"] < sessions["start"]).sum()
    assert raw.dropped["missing_location"] == n_missing > 0
    assert raw.dropped["zero_location"] == n_zero > 0
    assert raw.dropped["end_before_start"] == n_rev > 0
    assert raw.notes["crossing_midnight"] > 0
    # docs/PROTOCOL.md §4: about 85% zero cells after 470 m gridding and the trailing window.
    assert abs(stats.zero_cell_rate(raw.values) - 0.853) < 0.03
