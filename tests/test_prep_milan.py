"""Milan reader on raw-format lines rebuilt from the real shared series, crop geometry, demo statistics."""
from __future__ import annotations

import dataclasses
import datetime as dt
import gzip
from pathlib import Path

import numpy as np
import polars as pl
import yaml

from prep import milan, stats
from prep.config import datasets_config
from prep.demo.milan import generate

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT.parent / "shared" / "data" / "real" / "milan"
CET = dt.timezone(dt.timedelta(hours=1))


def _config():
    return datasets_config(yaml.safe_load((ROOT / "config.yaml").read_text())["datasets"]).milan


def _real_series() -> pl.DataFrame:
    """The two real 62-day series (square_id, time_interval_ms, internet as float32 values)."""
    parts = [pl.read_csv(REAL / f"ts_full_square_{sq}.csv", schema_overrides={"internet": pl.Float32})
             for sq in (4556, 5161)]
    return pl.concat(parts).select("square_id", pl.col("time_ms").alias("time_interval_ms"),
                                   pl.col("internet").cast(pl.Float64))


def _split_into_codes(values: np.ndarray, rng: np.random.Generator) -> list[np.ndarray]:
    """Three parts per value that add up exactly in float64: two float32 shares and the remainder."""
    a = (values * rng.uniform(0.6, 0.8, values.size)).astype(np.float32).astype(np.float64)
    b = (values * rng.uniform(0.1, 0.2, values.size)).astype(np.float32).astype(np.float64)
    c = values - a - b
    assert np.all((a + b) + c == values) and np.all((a + c) + b == values) and np.all((b + c) + a == values)
    return [a, b, c]


def _write_daily_files(series: pl.DataFrame, out: Path) -> list[Path]:
    """Writes the series as published daily files: country codes 39, 0, 33 plus an SMS-only line (blank internet)."""
    rng = np.random.default_rng(7)
    v = series["internet"].to_numpy()
    parts = _split_into_codes(v, rng)
    sq, t = series["square_id"].to_numpy(), series["time_interval_ms"].to_numpy()
    lines = []
    for code, part in zip((39, 0, 33), parts):
        lines.append(pl.DataFrame({"sq": sq, "t": t, "code": code, "sms_in": rng.uniform(0, 1, v.size),
                                   "sms_out": None, "call_in": None, "call_out": rng.uniform(0, 1, v.size),
                                   "internet": part}))
    lines.append(pl.DataFrame({"sq": sq, "t": t, "code": 44, "sms_in": 0.25, "sms_out": 0.5, "call_in": None,
                               "call_out": None, "internet": None}))
    df = pl.concat(lines, how="vertical_relaxed").sample(fraction=1.0, shuffle=True, seed=3)
    day = pl.from_epoch(df["t"], time_unit="ms").dt.replace_time_zone("UTC").dt.convert_time_zone("Europe/Rome") \
        .dt.date()
    df = df.with_columns(day.alias("day"))
    files = []
    for i, (key, part) in enumerate(sorted(df.group_by("day"), key=lambda kv: kv[0][0])):
        name = f"sms-call-internet-mi-{key[0].isoformat()}.txt"
        text = part.drop("day").write_csv(separator="\t", include_header=False, null_value="")
        if i % 2:
            path = out / (name + ".gz")
            path.write_bytes(gzip.compress(text.encode()))
        else:
            path = out / name
            path.write_text(text)
        files.append(path)
    return files


def test_reader_gives_the_real_series_back_exactly(tmp_path):
    series = _real_series()
    files = _write_daily_files(series, tmp_path)
    assert len(files) == 62 and sum(f.suffix == ".gz" for f in files) == 31
    got = milan.read_raw(files)
    want = series.sort("square_id", "time_interval_ms")
    assert got.height == 2 * 8928
    assert got["square_id"].to_list() == want["square_id"].to_list()
    assert got["time_interval_ms"].to_list() == want["time_interval_ms"].to_list()
    assert np.array_equal(got["internet"].to_numpy(), want["internet"].to_numpy())  # exact, not approximate


def test_reader_filters_squares_and_keeps_blank_only_slots_as_zero(tmp_path):
    path = tmp_path / "sms-call-internet-mi-2013-11-01.txt"
    path.write_text("4556\t1383260400000\t39\t1\t\t\t\t2.5\n"
                    "4556\t1383260400000\t0\t\t\t\t\t0.25\n"
                    "4557\t1383260400000\t39\t1\t2\t3\t4\t\n"
                    "4557\t1383260400000\t44\t1\t\t\t\t\n"
                    "9\t1383260400000\t39\t\t\t\t\t7\n")
    got = milan.read_raw([path], squares=[4556, 4557])
    assert got.rows() == [(4556, 1383260400000, 2.75), (4557, 1383260400000, 0.0)]


def test_central_crop_top5_share_from_real_totals_is_013():
    cfg = _config()
    totals = pl.read_csv(REAL / "square_totals_2mo.csv")
    frames = np.load(REAL / "milan_internet_grid_10min.npz")
    ids_north_up = frames["square_id"]  # row 0 = northernmost (independent statement of the id layout)
    grid_rows = 99 - np.arange(100)  # grid row counted from the south of each north-up row
    crop = cfg.crop
    want_ids = {int(ids_north_up[r, c]) for r in range(100) for c in range(100)
                if crop.first_row <= grid_rows[r] < crop.first_row + crop.rows
                and crop.first_col <= c < crop.first_col + crop.cols}
    rr, cc = np.meshgrid(np.arange(crop.rows), np.arange(crop.cols), indexing="ij")
    ids = (crop.first_row + rr) * 100 + crop.first_col + cc + 1
    assert set(ids.ravel().tolist()) == want_ids
    by_id = dict(zip(totals["square_id"].to_list(), totals["internet"].to_list()))
    v = np.array([by_id[i] for i in ids.ravel()])
    top = np.sort(v)[::-1][:20].sum() / v.sum()
    assert abs(top - 0.13) <= 0.005
    assert abs(stats.top_share(v.reshape(1, 1, 20, 20), 0.05) - top) < 1e-12


def test_build_maps_square_ids_to_rows_from_the_south(tmp_path):
    cfg = dataclasses.replace(_config(), split=dataclasses.replace(
        _config().split, train=("2013-11-01", "2013-11-01"), test=("2013-11-02", "2013-11-02")))
    # square 4041 = grid row 40, col 40 -> tensor (0, 0); square 5960 = row 59, col 59 -> (19, 19);
    # square 4160 = row 41, col 59 -> (1, 19). 2013-11-01 00:00 CET = 1383260400000, slot 7 = +70 min.
    t0 = 1383260400000
    lines = [f"4041\t{t0}\t39\t\t\t\t\t1.5", f"5960\t{t0 + 7 * 600000}\t39\t\t\t\t\t2", f"4160\t{t0}\t39\t\t\t\t\t3",
             f"4160\t{t0 + 86400000}\t39\t\t\t\t\t4", f"1\t{t0}\t39\t\t\t\t\t99"]
    a = tmp_path / "sms-call-internet-mi-2013-11-01.txt"
    b = tmp_path / "sms-call-internet-mi-2013-11-02.txt"
    a.write_text("\n".join(lines[:3] + lines[4:]) + "\n")
    b.write_text(lines[3] + "\n")
    raw = milan.build(cfg, [a, b, tmp_path / "sms-call-internet-mi-2013-11-20.txt"])
    assert raw.values.shape == (2, 144, 20, 20)
    assert raw.values[0, 0, 0, 0] == 1.5 and raw.values[0, 7, 19, 19] == 2 and raw.values[0, 0, 1, 19] == 3
    assert raw.values[1, 0, 1, 19] == 4 and raw.values.sum() == 10.5
    assert raw.notes["files_skipped_outside_segments"] == 1 and raw.dropped == {"duplicate_lines": 0}
    assert [d.label for d in raw.days] == ["2013-11-01", "2013-11-02"] and raw.weekday == [4, 5]


def test_demo_files_are_published_format_and_driven_by_real_totals(tmp_path):
    base = _config()
    cfg = dataclasses.replace(base, split=dataclasses.replace(
        base.split, train=("2013-11-04", "2013-11-04"), test=("2013-12-25", "2013-12-25")))
    files = generate(cfg, tmp_path)
    assert [f.name for f in files] == ["sms-call-internet-mi-2013-11-04.txt", "sms-call-internet-mi-2013-12-25.txt"]
    lines = files[0].read_text().splitlines()
    fields = [ln.split("\t") for ln in lines[:2000]]
    assert all(len(f) == 8 for f in fields)
    assert any(f[7] == "" for f in fields)  # blank internet on some country-code lines
    per_slot = {}
    for f in fields:
        per_slot.setdefault((f[0], f[1]), []).append(f[2])
    assert max(len(v) for v in per_slot.values()) >= 3  # several country codes per square and slot
    ids = {int(f.split("\t", 1)[0]) for f in lines}
    assert ids == {r * 100 + c + 1 for r in range(40, 60) for c in range(40, 60)}
    assert int(lines[0].split("\t")[1]) == 1383519600000  # 2013-11-04 00:00 CET
    # Twice with the same seed: identical bytes.
    again = generate(cfg, tmp_path / "again")
    assert [f.read_bytes() for f in files] == [f.read_bytes() for f in again]
    raw = milan.build(cfg, files)
    monday, christmas = raw.values[0], raw.values[1]
    # The real Christmas day is far quieter than a November Monday (real series: about half).
    assert christmas.sum() < 0.75 * monday.sum()
    # Hotspots move: the top 20 cells at 04:00 and at 14:00 of the Monday share fewer than half their members.
    top = lambda m: set(np.argsort(-m.ravel())[:20].tolist())  # noqa: E731
    assert len(top(monday[24:30].mean(0)) & top(monday[84:90].mean(0))) < 10
