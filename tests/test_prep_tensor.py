"""Training-only normalization, kappa, meta.json keys, long-form Parquet and load() round trip."""
from __future__ import annotations

import copy
import json
import zoneinfo
from pathlib import Path

import numpy as np
import polars as pl
import pytest
import yaml


from prep.tensor import load

from conftest import prepare_from_config

ROOT = Path(__file__).resolve().parents[1]
META_KEYS = {"dataset", "source", "grid", "slots_per_day", "days", "split", "eval_days", "p99", "p99_all_days", "notes",
             "kappa", "kappa_reference_mean", "train_mean_normalized", "week", "zero_cell_rate", "top5_share", "crop",
             "sources", "dropped", "config", "empty_days"}
DAYS = ["2013-11-01", "2013-11-02", "2013-12-21", "2013-12-22"]  # 2 training days, 2 test days


def small_milan_config(raw_glob: str) -> dict:
    """The repository config with a 2+2-day Milan split reading `raw_glob`."""
    config = copy.deepcopy(yaml.safe_load((ROOT / "config.yaml").read_text()))
    m = config["datasets"]["milan"]
    m.update(source="raw", raw_files=[raw_glob])
    m["split"] = {"train": DAYS[:2], "test": DAYS[2:]}
    m["eval_days"] = {"id": {"rule": "test_positions", "values": [0], "count": 1},
                      "ood": {"rule": "test_positions", "values": [1], "count": 1}}
    return config


def write_milan_days(out: Path, values: np.ndarray) -> None:
    """Writes (4, 144, 20, 20) crop values as daily files, each value split over two country codes."""
    tz = zoneinfo.ZoneInfo("Europe/Rome")
    import datetime as dt

    for k, day in enumerate(DAYS):
        t0 = int(dt.datetime.fromisoformat(day).replace(tzinfo=tz).timestamp() * 1000)
        s, r, c = np.meshgrid(np.arange(144), np.arange(20), np.arange(20), indexing="ij")
        sq = ((40 + r) * 100 + 40 + c + 1).ravel()
        t = (t0 + 600_000 * s).ravel()
        v = values[k].ravel()
        half = np.floor(v * 0.5 * 8) / 8  # exact binary fractions: the sum is exact
        df = pl.concat([pl.DataFrame({"a": sq, "b": t, "c": 39, "d": None, "e": None, "f": None, "g": None,
                                      "h": half}),
                        pl.DataFrame({"a": sq, "b": t, "c": 33, "d": 1.0, "e": None, "f": None, "g": None,
                                      "h": v - half})], how="vertical_relaxed")
        df.write_csv(out / f"sms-call-internet-mi-{day}.txt", separator="\t", include_header=False, null_value="")


def test_p99_uses_training_days_only_and_load_round_trips(tmp_path):
    rng = np.random.default_rng(1)
    values = np.round(rng.gamma(2.0, 10.0, (4, 144, 20, 20)) * 8) / 8
    values[2:] *= 5.0  # test days far busier: the all-days percentile differs
    raw_dir = tmp_path / "raw"
    raw_dir.mkdir()
    write_milan_days(raw_dir, values)
    out = tmp_path / "data" / "milan"
    meta = prepare_from_config(small_milan_config(str(raw_dir / "*.txt")), "milan", raw=[str(raw_dir)], out_dir=out,
                           reference_meta=None)
    train_p99 = float(np.percentile(values[:2].ravel(), 99))
    all_p99 = float(np.percentile(values.ravel(), 99))
    assert meta["p99"] == pytest.approx(train_p99, rel=1e-12)
    assert meta["p99_all_days"] == pytest.approx(all_p99, rel=1e-12) and abs(all_p99 - train_p99) > 1.0
    assert meta["kappa"] == 1.0
    assert meta["train_mean_normalized"] == pytest.approx(values[:2].mean() / train_p99, rel=1e-9)
    assert set(meta) >= META_KEYS
    assert [d["label"] for d in meta["days"]] == DAYS
    assert [d["split"] for d in meta["days"]] == ["train", "train", "test", "test"]
    assert meta["eval_days"] == {"id": [2], "ood": [3]}
    assert {s["name"] for s in meta["sources"]} == {f"sms-call-internet-mi-{d}.txt" for d in DAYS}
    t = load(out)
    assert t.demand.dtype == np.float32 and t.demand.shape == (4, 144, 20, 20)
    assert np.allclose(t.demand, values / train_p99, rtol=1e-6)
    assert t.train_days.tolist() == [0, 1] and t.test_days.tolist() == [2, 3]
    assert t.eval_days("ood").tolist() == [3] and (t.grid.rows, t.grid.cols, t.grid.cell_m) == (20, 20, 235.0)
    df = pl.read_parquet(out / "demand.parquet")
    assert dict(df.schema) == {"day": pl.Int32, "slot": pl.Int16, "row": pl.Int16, "col": pl.Int16,
                               "demand": pl.Float32}
    assert sorted(p.name for p in out.iterdir()) == ["demand.parquet", "meta.json"]  # no temporaries left


def test_kappa_aligns_the_training_mean_with_the_reference(tmp_path):
    config = copy.deepcopy(yaml.safe_load((ROOT / "config.yaml").read_text()))
    y = config["datasets"]["yjmob"]
    y.update(source="raw", raw_files=[str(tmp_path / "y.csv")], n_days=14)
    y["split"] = {"train": [0, 9], "test": [10, 13]}
    y["crop"] = {"rows": 2, "cols": 2}
    y["week"] = {"min_lag": 2, "max_lag": 4, "n_weekend_phases": 1}
    y["eval_days"] = {"id": {"rule": "test_positions", "values": [0], "count": 1},
                      "ood": {"rule": "test_positions", "values": [1], "count": 1}}
    rows = ["uid,d,t,x,y"]
    rng = np.random.default_rng(2)
    dense = np.zeros((14, 48, 2, 2))
    for d in range(14):
        for t in range(0, 48, 3):
            for uid in range(int(rng.integers(1, 6))):
                x, yy = 10 + uid % 2, 20 + (uid // 2) % 2
                rows.append(f"{uid},{d},{t},{x},{yy}")
                dense[d, t, yy - 20, x - 10] += 1
    (tmp_path / "y.csv").write_text("\n".join(rows) + "\n")
    ref = tmp_path / "milan_meta.json"
    ref.write_text(json.dumps({"dataset": "milan", "train_mean_normalized": 0.3, "kappa": 1.0}))
    meta = prepare_from_config(config, "yjmob", raw=[str(tmp_path / "y.csv")], out_dir=tmp_path / "out",
                           reference_meta=str(ref))
    ten = np.repeat(dense / 3, 3, axis=1)
    p99 = float(np.percentile(ten[:10].ravel(), 99))
    train_mean = ten[:10].mean() / p99
    assert meta["p99"] == pytest.approx(p99) and meta["kappa"] == pytest.approx(0.3 / train_mean)
    assert meta["kappa_reference_mean"] == 0.3
    t = load(tmp_path / "out")
    assert t.demand[t.train_days].mean() == pytest.approx(0.3, rel=1e-5)  # aligned to the reference
    assert t.meta["week"]["lag"] in (2, 3, 4) and [d["label"] for d in t.meta["days"]][:2] == ["d0", "d1"]


@pytest.fixture(scope="module")
def prepared(tmp_path_factory):
    """A prepared 2+2-day Milan directory (demand.parquet + meta.json)."""
    root = tmp_path_factory.mktemp("prepared")
    (root / "raw").mkdir()
    write_milan_days(root / "raw", np.full((4, 144, 20, 20), 2.0))
    prepare_from_config(small_milan_config(str(root / "raw" / "*.txt")), "milan", raw=[str(root / "raw")],
                    out_dir=root / "milan", reference_meta=None)
    return root / "milan"


@pytest.mark.parametrize("corrupt, words", [
    (lambda text, meta: text[: len(text) // 2], ["not valid JSON"]),
    (lambda text, meta: json.dumps({k: v for k, v in meta.items() if k != "slots_per_day"}),
     ["missing key 'slots_per_day'", "an integer"]),
    (lambda text, meta: json.dumps({**meta, "grid": {**meta["grid"], "rows": "20"}}),
     ["'grid.rows'", "a number", "'20'"]),
    (lambda text, meta: json.dumps({**meta, "days": [{"index": 0}] + meta["days"][1:]}),
     ["days[0] lacks ['label', 'split']"]),
])
def test_a_malformed_meta_json_is_named_with_its_key(prepared, tmp_path, corrupt, words):
    import shutil

    from prep.rawio import PrepError

    out = tmp_path / "milan"
    shutil.copytree(prepared, out)
    assert load(out).demand.shape == (4, 144, 20, 20)   # intact: loads
    text = (out / "meta.json").read_text()
    (out / "meta.json").write_text(corrupt(text, json.loads(text)))
    with pytest.raises(PrepError) as err:
        load(out)
    msg = str(err.value)
    assert msg.startswith(str(out / "meta.json")), msg
    for w in words:
        assert w in msg, f"{w!r} not in: {msg}"
