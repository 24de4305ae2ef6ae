"""Every bad raw input stops preparation with an error naming the file (and row) and leaves no output."""
from __future__ import annotations

import copy
import gzip
from pathlib import Path

import polars as pl
import pytest
import yaml

from prep.demo.shanghai import _write_xlsx
from prep.pipeline import raw_inputs
from prep.rawio import PrepError

from conftest import prepare_from_config, dataset_of

ROOT = Path(__file__).resolve().parents[1]
T0 = 1383260400000  # 2013-11-01 00:00 CET
MILAN_OK = f"4041\t{T0}\t39\t\t\t\t\t1.5\n4042\t{T0}\t39\t1\t\t\t\t2.5\n"
YJ_HEADER = "uid,d,t,x,y\n"
SH_COLUMNS = ["month", "date", "start time", "end time", "latitude", "longitude", "user id"]
SH_OK = (201406, 20140601, "2014-06-01 08:00:00", "2014-06-01 08:10:00", 31.23, 121.47, "a")


def _config() -> dict:
    config = copy.deepcopy(yaml.safe_load((ROOT / "config.yaml").read_text()))
    d = config["datasets"]
    positions = {"id": {"rule": "test_positions", "values": [0], "count": 1},
                 "ood": {"rule": "test_positions", "values": [1], "count": 1}}
    d["milan"]["split"] = {"train": ["2013-11-01", "2013-11-01"], "test": ["2013-11-02", "2013-11-03"]}
    d["yjmob"]["split"] = {"train": [0, 1], "test": [2, 3]}
    d["shanghai"]["split"] = {"train": ["2014-06-01", "2014-06-01"], "test": ["2014-06-02", "2014-06-03"]}
    for name in ("milan", "shanghai", "yjmob"):
        d[name]["eval_days"] = copy.deepcopy(positions)
    return config


def _milan(tmp: Path, body: str, *, name="sms-call-internet-mi-2013-11-01.txt", gz=False) -> Path:
    path = tmp / (name + (".gz" if gz else ""))
    data = body.encode()
    path.write_bytes(gzip.compress(data) if gz else data)
    for k in (1, 2):
        (tmp / f"sms-call-internet-mi-2013-11-0{k + 1}.txt").write_text(f"4041\t{T0 + k * 86_400_000}\t39\t\t\t\t\t1\n")
    return path


def _yjmob(tmp: Path, body: str, *, gz=False) -> Path:
    path = tmp / ("yjmob100k-dataset1.csv" + (".gz" if gz else ""))
    path.write_bytes(gzip.compress(body.encode()) if gz else body.encode())
    return path


def _shanghai(tmp: Path, rows, columns=SH_COLUMNS) -> Path:
    path = tmp / "data_6.1~6.15.xlsx"
    _write_xlsx(path, pl.DataFrame(rows, schema=columns, orient="row"))
    return path


def _truncate(path: Path) -> Path:
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    return path


YJ_BODY = YJ_HEADER + "".join(f"{u},{d},{t},5,5\n" for u in range(3) for d in range(4) for t in range(48))
MILAN_BIG = "".join(f"{4041 + k}\t{T0 + 600_000 * s}\t39\t\t\t\t\t{k + s}.25\n" for k in range(20) for s in range(144))

CASES = {
    # name: (dataset, writer(tmp) -> bad file, words the message must contain)
    "milan_missing_file": ("milan", lambda t: t / "sms-call-internet-mi-2013-11-01.txt", ["no such file"]),
    "milan_too_few_fields": ("milan", lambda t: _milan(t, MILAN_OK + f"4041\t{T0}\t39\t\t\t1.5\n"),
                             ["Expected 8 columns"]),
    "milan_non_numeric": ("milan", lambda t: _milan(t, MILAN_OK + f"4041\t{T0}\t39\t\t\t\t\tabc\n"),
                          ["line 3", "'internet'", "'abc'"]),
    "milan_negative": ("milan", lambda t: _milan(t, MILAN_OK + f"4041\t{T0}\t39\t\t\t\t\t-2.0\n"),
                       ["line 3", "count >= 0", "-2.0"]),
    "milan_square_outside_grid": ("milan", lambda t: _milan(t, MILAN_OK + f"10001\t{T0}\t39\t\t\t\t\t1\n"),
                                  ["line 3", "1..10000", "10001"]),
    "milan_date_outside_segments": ("milan", lambda t: _milan(t, MILAN_OK + f"4041\t{T0 - 600_000}\t39\t\t\t\t\t1\n"),
                                    ["line 3", "configured segment"]),
    "milan_empty_crop": ("milan", lambda t: _milan(t, f"1\t{T0}\t39\t\t\t\t\t1\n".replace("\n", "\n") * 1),
                         ["crop"]),
    "milan_truncated_gz": ("milan", lambda t: _truncate(_milan(t, MILAN_BIG * 4, gz=True)), ["truncated"]),
    "yjmob_renamed_column": ("yjmob", lambda t: _yjmob(t, "uid,day,t,x,y\n1,0,0,5,5\n"),
                             ["line 1", "missing column", "'d'"]),
    "yjmob_non_numeric": ("yjmob", lambda t: _yjmob(t, YJ_BODY + "1,1,3,five,5\n"), [f"line {YJ_BODY.count(chr(10)) + 1}",
                                                                                  "'x'", "'five'"]),
    "yjmob_negative_uid": ("yjmob", lambda t: _yjmob(t, YJ_HEADER + "-4,0,0,5,5\n"), ["line 2", "'uid'", "-4"]),
    "yjmob_outside_grid": ("yjmob", lambda t: _yjmob(t, YJ_BODY + "7,1,3,201,5\n"),
                           [f"line {YJ_BODY.count(chr(10)) + 1}", "1..200", "x=201"]),
    "yjmob_day_outside_segments": ("yjmob", lambda t: _yjmob(t, YJ_BODY + "7,40,3,5,5\n"),
                                   [f"line {YJ_BODY.count(chr(10)) + 1}", "configured segment", "d=40"]),
    "yjmob_empty_crop": ("yjmob", lambda t: _yjmob(t, YJ_HEADER + "".join(f"1,2,{k},5,5\n" for k in range(4))),
                         ["no record for day"]),
    "yjmob_truncated_gz": ("yjmob", lambda t: _truncate(_yjmob(t, YJ_BODY * 30, gz=True)), ["truncated"]),
    "shanghai_renamed_column": ("shanghai", lambda t: _shanghai(t, [SH_OK], SH_COLUMNS[:4] + ["lat"] + SH_COLUMNS[5:]),
                                ["row 1", "missing column", "'latitude'"]),
    "shanghai_non_numeric": ("shanghai", lambda t: _shanghai(t, [SH_OK, SH_OK[:4] + ("north",) + SH_OK[5:]]),
                             ["row 3", "'latitude'", "'north'"]),
    "shanghai_bad_time": ("shanghai", lambda t: _shanghai(t, [SH_OK, ("x", "y", "June 1st", "z", 31.2, 121.4, "b")]),
                          ["row 3", "'start time'", "June 1st"]),
    "shanghai_outside_grid": ("shanghai", lambda t: _shanghai(t, [SH_OK, SH_OK[:4] + (39.9, 116.4) + SH_OK[6:]]),
                              ["row 3", "lat 30.69..31.51", "39.9"]),
    "shanghai_date_outside_segments": ("shanghai", lambda t: _shanghai(
        t, [SH_OK, SH_OK[:2] + ("2014-12-05 08:00:00", "2014-12-05 08:10:00") + SH_OK[4:]]),
        ["row 3", "configured segment", "2014-12-05"]),
    "shanghai_empty_crop": ("shanghai", lambda t: _shanghai(t, [SH_OK[:4] + (None, None) + SH_OK[6:]]),
                            ["no valid session"]),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_input_names_the_file_and_leaves_no_output(tmp_path, case):
    dataset, make, words = CASES[case]
    raw_dir = tmp_path / "raw"
    raw_dir.mkdir()
    bad = make(raw_dir)
    out = tmp_path / "data" / dataset
    out.mkdir(parents=True)
    ref = tmp_path / "milan_meta.json"
    ref.write_text('{"dataset": "milan", "train_mean_normalized": 0.2, "kappa": 1.0}')
    config = _config()
    config["datasets"][dataset]["raw_files"] = [str(bad)]
    config["datasets"][dataset]["source"] = "raw"
    with pytest.raises(PrepError) as err:
        prepare_from_config(config, dataset, raw=[str(bad)] if bad.exists() else [str(bad)], out_dir=out,
                        reference_meta=None if dataset == "milan" else str(ref))
    msg = str(err.value)
    if not case.endswith("empty_crop"):
        assert bad.name in msg, msg
    for w in words:
        assert w in msg, msg
    assert list(out.iterdir()) == []  # nothing written, no temporary left


def test_missing_raw_file_is_reported_when_the_rule_inputs_are_built(tmp_path):
    config = _config()
    config["datasets"]["yjmob"].update(source="raw", raw_files=[str(tmp_path / "nowhere" / "*.csv.gz")])
    with pytest.raises(PrepError, match="nowhere"):
        raw_inputs(dataset_of(config, "yjmob"), "yjmob")
    config["datasets"]["yjmob"]["source"] = "demo"
    assert raw_inputs(dataset_of(config, "yjmob"), "yjmob") == ["results/raw/yjmob/demo"]


def test_a_failure_after_writing_leaves_no_partial_output(tmp_path, monkeypatch):
    from prep import tensor

    raw_dir = tmp_path / "raw"
    raw_dir.mkdir()
    _milan(raw_dir, MILAN_BIG)
    out = tmp_path / "out"

    def broken(self, *a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(pl.DataFrame, "write_parquet", broken)
    config = _config()
    with pytest.raises(OSError, match="disk full"):
        prepare_from_config(config, "milan", raw=[str(raw_dir)], out_dir=out, reference_meta=None)
    assert list(out.iterdir()) == []
    assert tensor.META_FILE == "meta.json"


def test_drop_mode_drops_and_counts_out_of_range_rows(tmp_path):
    raw_dir = tmp_path / "raw"
    raw_dir.mkdir()
    _milan(raw_dir, MILAN_BIG + f"10001\t{T0}\t39\t\t\t\t\t1\n" + f"4041\t{T0 - 600_000}\t39\t\t\t\t\t1\n" * 2)
    config = _config()
    config["datasets"]["milan"]["on_out_of_range"] = "drop"
    meta = prepare_from_config(config, "milan", raw=[str(raw_dir)], out_dir=tmp_path / "out", reference_meta=None)
    assert meta["dropped"] == {"square_outside_grid": 1, "outside_segments": 2, "duplicate_lines": 0}
    body = YJ_HEADER + "".join(f"{u},{d},{t},5,5\n" for u in range(3) for d in range(6) for t in range(48))
    bad = _yjmob(raw_dir, body + "7,1,3,201,5\n7,40,3,5,5\n7,41,3,5,5\n")
    config["datasets"]["yjmob"]["on_out_of_range"] = "drop"
    config["datasets"]["yjmob"]["split"] = {"train": [0, 3], "test": [4, 5]}
    ref = tmp_path / "milan_meta.json"
    ref.write_text('{"dataset": "milan", "train_mean_normalized": 0.2, "kappa": 1.0}')
    meta = prepare_from_config(config, "yjmob", raw=[str(bad)], out_dir=tmp_path / "out_y", reference_meta=str(ref))
    assert meta["dropped"] == {"cell_outside_grid": 1, "outside_segments": 2, "masked_999": 0,
                               "duplicate_records": 0}
