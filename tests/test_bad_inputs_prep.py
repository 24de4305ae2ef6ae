"""Bad input never yields a table: every malformed raw input or day setting stops with an exact message.

Raw inputs are tiny files in the published formats, written to tmp_path; preparation must leave nothing
behind on an error (no demand.parquet, no meta.json, no temporary). Day settings are refused when the config
is resolved (`dswm.settings.resolve`, as the Snakefile does), before any job. A day to evaluate with a slot
of zero total demand is refused before any controller runs.
"""
from __future__ import annotations

import copy
import gzip
from pathlib import Path

import numpy as np
import polars as pl
import pyarrow as pa
import pytest
import yaml

from dswm.config import ConfigError
from dswm.methods.classical import StaticController
from dswm.protocol.evaluation import evaluate
from dswm.settings import resolve
from prep.demo.shanghai import _write_xlsx
from prep.rawio import PrepError
from prep.tensor import DemandTensor, GridSpec, load

from conftest import dataset_of, prepare_from_config

ROOT = Path(__file__).resolve().parents[1]
T0 = 1383260400000  # 2013-11-01 00:00 CET in ms
DAY_MS = 86_400_000
SLOT_MS = 600_000
MILAN_FIELDS = ("['square_id', 'time_interval_ms', 'country_code', 'sms_in', 'sms_out', 'call_in', 'call_out', "
                "'internet']")
SH_COLUMNS = ["month", "date", "start time", "end time", "latitude", "longitude", "user id"]
SH_FIELDS = "['month', 'date', 'start time', 'end time', 'latitude', 'longitude', 'user id']"
YJ_FIELDS = "['uid', 'd', 't', 'x', 'y']"
POSITIONS = {"id": {"rule": "test_positions", "values": [0], "count": 1},
             "ood": {"rule": "test_positions", "values": [1], "count": 1}}


def _config() -> dict:
    """The repository config with 2 + 2-day splits, a 2 x 2 crop and eval days = test positions 0 and 1."""
    config = copy.deepcopy(yaml.safe_load((ROOT / "config.yaml").read_text()))
    d = config["datasets"]
    d["milan"]["split"] = {"train": ["2013-11-01", "2013-11-02"], "test": ["2013-11-03", "2013-11-04"]}
    d["milan"]["crop"] = {"first_row": 40, "first_col": 40, "rows": 2, "cols": 2}
    d["shanghai"]["split"] = {"train": ["2014-06-14", "2014-06-15"], "test": ["2014-06-16", "2014-06-17"]}
    d["shanghai"]["crop"] = {"rows": 2, "cols": 2}
    d["yjmob"]["split"] = {"train": [0, 1], "test": [2, 3]}
    for name in ("milan", "shanghai", "yjmob"):
        d[name].update(source="raw", eval_days=copy.deepcopy(POSITIONS), allow_empty_days=[])
    return config


def _prepare(config: dict, dataset: str, raw: list[Path], out: Path, tmp: Path) -> dict:
    ref = tmp / "milan_meta.json"
    ref.write_text('{"dataset": "milan", "train_mean_normalized": 0.2, "kappa": 1.0}')
    return prepare_from_config(config, dataset, raw=[str(p) for p in raw], out_dir=out,
                               reference_meta=None if dataset == "milan" else str(ref))


def _refused(config: dict, dataset: str, raw: list[Path], tmp: Path, error=PrepError) -> str:
    """Prepares into a fresh output directory, expects `error`, checks that nothing was left there."""
    out = tmp / "data" / dataset
    out.mkdir(parents=True)
    with pytest.raises(error) as err:
        _prepare(config, dataset, raw, out, tmp)
    assert list(out.iterdir()) == []  # no demand.parquet, no meta.json, no temporary
    return str(err.value)


def _milan_day(raw: Path, k: int, *, extra: str = "", suffix: str = ".txt") -> Path:
    """Day 2013-11-0{k+1}: square 4041 (crop row 0, col 0) in every slot, plus `extra` lines."""
    t = T0 + k * DAY_MS
    body = "".join(f"4041\t{t + SLOT_MS * s}\t39\t\t\t\t\t{1 + s % 7}.5\n" for s in range(144)) + extra
    path = raw / f"sms-call-internet-mi-2013-11-0{k + 1}{suffix}"
    path.write_bytes(gzip.compress(body.encode()) if suffix.endswith(".gz") else body.encode())
    return path


def _sessions(days: list[str], per_day: int = 24) -> list[tuple]:
    """Sessions at People's Square, one an hour on each day (so every training day has crop demand)."""
    return [(201406, int(day.replace("-", "")), f"{day} {h:02d}:05:00", f"{day} {h:02d}:25:00", 31.2304, 121.4737,
             f"u{h}") for day in days for h in range(per_day)]


def _workbook(path: Path, rows: list[tuple]) -> Path:
    _write_xlsx(path, pl.DataFrame(rows, schema=SH_COLUMNS, orient="row"))
    return path


def _yjmob(raw: Path, days: list[int]) -> Path:
    path = raw / "yjmob100k-dataset1.csv"
    path.write_text("uid,d,t,x,y\n" + "".join(f"{u},{d},{t},5,5\n" for u in range(3) for d in days for t in range(48)))
    return path


@pytest.fixture
def raw(tmp_path) -> Path:
    path = tmp_path / "raw"
    path.mkdir()
    return path


# ---------------------------------------------------------------------------- every configured day has data


def test_a_missing_shanghai_workbook_is_refused(tmp_path, raw):
    first = _workbook(raw / "data_6.1~6.15.xlsx", _sessions(["2014-06-14", "2014-06-15"]))
    msg = _refused(_config(), "shanghai", [first], tmp_path)
    assert msg == (f"shanghai: no session for day(s) ['2014-06-16', '2014-06-17'] of the configured segments, in "
                   f"the 1 file(s) read from {raw}: ['data_6.1~6.15.xlsx']; expected sessions on every configured "
                   f"day (e.g. the half-month workbook data_6.16~6.30.xlsx among the raw files), or the day(s) "
                   f"listed in datasets.shanghai.allow_empty_days")


def test_an_empty_milan_day_is_refused(tmp_path, raw):
    files = [_milan_day(raw, k) for k in (0, 2, 3)]  # 2013-11-02 has no file
    msg = _refused(_config(), "milan", [raw], tmp_path)
    assert msg == (f"milan: no line in the crop for day(s) ['2013-11-02'] of the configured segments, in the 3 "
                   f"file(s) read from {raw}: {[f.name for f in files]}; expected files such as "
                   f"sms-call-internet-mi-2013-11-02.txt among the raw files, or the day(s) listed in "
                   f"datasets.milan.allow_empty_days")


def test_a_milan_day_whose_lines_all_lie_outside_the_crop_is_empty(tmp_path, raw):
    for k in (0, 2, 3):
        _milan_day(raw, k)
    outside = raw / "sms-call-internet-mi-2013-11-02.txt"
    outside.write_text(f"1\t{T0 + DAY_MS}\t39\t\t\t\t\t4.0\n")  # square 1: grid row 0, far from the crop
    msg = _refused(_config(), "milan", [raw], tmp_path)
    names = [f"sms-call-internet-mi-2013-11-0{k}.txt" for k in (1, 2, 3, 4)]
    assert msg == (f"milan: no line in the crop for day(s) ['2013-11-02'] of the configured segments, in the 4 "
                   f"file(s) read from {raw}: {names}; expected files such as sms-call-internet-mi-2013-11-02.txt "
                   f"among the raw files, or the day(s) listed in datasets.milan.allow_empty_days")


def test_an_empty_yjmob_day_is_refused(tmp_path, raw):
    path = _yjmob(raw, [0, 2, 3])
    msg = _refused(_config(), "yjmob", [path], tmp_path)
    assert msg == (f"yjmob: no record for day(s) ['d1'] of the configured segments, in the 1 file(s) read from "
                   f"{raw}: ['yjmob100k-dataset1.csv']; expected records (uid,d,t,x,y) on every configured day, or "
                   f"the day(s) listed in datasets.yjmob.allow_empty_days")


def test_the_allowance_accepts_a_listed_empty_training_day(tmp_path, raw):
    for k in (0, 2, 3):
        _milan_day(raw, k)
    config = _config()
    config["datasets"]["milan"]["allow_empty_days"] = ["2013-11-02"]
    resolve(config)  # a training day may be listed
    out = tmp_path / "data" / "milan"
    meta = _prepare(config, "milan", [raw], out, tmp_path)
    assert meta["empty_days"] == ["2013-11-02"]
    t = load(out)
    assert t.demand[1].sum() == 0 and t.demand[[0, 2, 3]].sum(axis=(1, 2, 3)).min() > 0


def test_the_allowance_of_an_empty_shanghai_test_day_that_is_no_eval_day(tmp_path, raw):
    config = _config()
    config["datasets"]["shanghai"]["split"]["test"] = ["2014-06-16", "2014-06-18"]  # 2014-06-18: no eval day
    config["datasets"]["shanghai"]["allow_empty_days"] = ["2014-06-18"]
    book = _workbook(raw / "data_6.16~6.30.xlsx", _sessions(["2014-06-14", "2014-06-15", "2014-06-16", "2014-06-17"]))
    meta = _prepare(config, "shanghai", [book], tmp_path / "out", tmp_path)
    assert meta["empty_days"] == ["2014-06-18"] and meta["eval_days"] == {"id": [2], "ood": [3]}


@pytest.mark.parametrize("dataset, day, expected", [
    ("milan", "2013-12-21", "config key datasets.milan.allow_empty_days[0]: expected a day that is not an "
     "evaluation day (an evaluation day may never be empty), found '2013-12-21', a datasets.milan.eval_days.id day"),
    ("shanghai", "2014-11-01", "config key datasets.shanghai.allow_empty_days[0]: expected a day that is not an "
     "evaluation day (an evaluation day may never be empty), found '2014-11-01', a datasets.shanghai.eval_days.ood "
     "day"),  # the first Saturday of the test month: the rule first_weekend picks it
    ("yjmob", 60, "config key datasets.yjmob.allow_empty_days[0]: expected a training day (an evaluation day may "
     "never be empty, and a first_weekdays/first_weekend rule of datasets.yjmob.eval_days picks test days by the "
     "week recovered from the data, so any test day may be one), found 60"),
    ("milan", "2013-11-20", "config key datasets.milan.allow_empty_days[0]: expected a day of the training or test "
     "segment (2013-11-01..2013-11-10, 2013-12-21..2014-01-01), found '2013-11-20'"),
])
def test_the_allowance_of_an_evaluation_day_is_refused_when_the_config_is_read(dataset, day, expected):
    config = copy.deepcopy(yaml.safe_load((ROOT / "config.yaml").read_text()))
    config["datasets"][dataset]["allow_empty_days"] = [day]
    with pytest.raises(ConfigError) as err:
        resolve(config)
    assert str(err.value) == expected
    with pytest.raises(ConfigError) as err:  # a job's own slice is checked the same way
        dataset_of(config, dataset)
    assert str(err.value) == expected


# ---------------------------------------------------------------------------- one source per date, duplicates


def test_a_milan_day_present_as_txt_and_txt_gz_is_refused(tmp_path, raw):
    for k in (1, 2, 3):
        _milan_day(raw, k)
    plain, packed = _milan_day(raw, 0), _milan_day(raw, 0, suffix=".txt.gz")
    msg = _refused(_config(), "milan", [raw], tmp_path)
    assert msg == (f"milan: day 2013-11-01 has 2 raw files: {plain}, {packed}; expected one source per date (keep "
                   f"one of them)")


def test_exact_duplicate_milan_lines_are_dropped_and_counted(tmp_path, raw):
    clean, dup = raw / "clean", raw / "dup"
    clean.mkdir()
    dup.mkdir()
    for k in range(4):
        # three exact repeats of a day's lines; a line that differs from a kept one only in its SMS field is kept
        repeat = "".join(f"4041\t{T0 + k * DAY_MS + SLOT_MS * s}\t39\t\t\t\t\t{1 + s % 7}.5\n" for s in range(3))
        other = f"4041\t{T0}\t39\t2\t\t\t\t1.5\n" if k == 0 else ""
        _milan_day(clean, k, extra=other)
        _milan_day(dup, k, extra=repeat + other)
    m_clean = _prepare(_config(), "milan", [clean], tmp_path / "a", tmp_path)
    m_dup = _prepare(_config(), "milan", [dup], tmp_path / "b", tmp_path)
    assert m_clean["dropped"] == {"duplicate_lines": 0}
    assert m_dup["dropped"] == {"duplicate_lines": 12}
    assert np.array_equal(load(tmp_path / "a").demand, load(tmp_path / "b").demand)


def test_exact_duplicate_shanghai_rows_are_dropped_and_counted(tmp_path, raw):
    days = ["2014-06-14", "2014-06-15", "2014-06-16", "2014-06-17"]
    rows = _sessions(days)
    once = _workbook(raw / "data_6.1~6.15.xlsx", rows)
    m_once = _prepare(_config(), "shanghai", [once], tmp_path / "a", tmp_path)
    (raw / "copy").mkdir()
    twice = _workbook(raw / "copy" / "data_6.1~6.15 (1).xlsx", rows + rows[:5])  # the workbook again, 5 rows twice
    m_twice = _prepare(_config(), "shanghai", [once, twice], tmp_path / "b", tmp_path)
    assert m_once["dropped"] == {"duplicate_rows": 0, "end_before_start": 0, "missing_location": 0,
                                 "zero_location": 0}
    assert m_twice["dropped"] == {"duplicate_rows": len(rows) + 5, "end_before_start": 0, "missing_location": 0,
                                  "zero_location": 0}
    assert np.array_equal(load(tmp_path / "a").demand, load(tmp_path / "b").demand)


# ---------------------------------------------------------------------------- empty files


@pytest.mark.parametrize("dataset, name, expected", [
    ("yjmob", "yjmob100k-dataset1.csv.gz", f"a header line with the columns {YJ_FIELDS}, then one line per record"),
    ("yjmob", "yjmob100k-dataset1.csv", f"a header line with the columns {YJ_FIELDS}, then one line per record"),
    ("milan", "sms-call-internet-mi-2013-11-01.txt", f"lines of 8 fields {MILAN_FIELDS}"),
    ("milan", "sms-call-internet-mi-2013-11-01.txt.gz", f"lines of 8 fields {MILAN_FIELDS}"),
    ("shanghai", "data_6.1~6.15.xlsx", f"an Excel workbook with the columns {SH_FIELDS}"),
    ("shanghai", "export.csv", f"a header line with the columns {SH_FIELDS}, then one line per record"),
])
def test_a_zero_byte_file_is_an_empty_file(tmp_path, raw, dataset, name, expected):
    if dataset == "milan":
        for k in (1, 2, 3):
            _milan_day(raw, k)
    bad = raw / name
    bad.write_bytes(b"")
    msg = _refused(_config(), dataset, [raw], tmp_path)
    assert msg == f"{bad}: empty file (0 bytes); expected {expected}"


def test_a_gz_holding_nothing_is_an_empty_file(tmp_path, raw):
    bad = raw / "yjmob100k-dataset1.csv.gz"
    bad.write_bytes(gzip.compress(b""))
    msg = _refused(_config(), "yjmob", [bad], tmp_path)
    assert msg == (f"{bad}: empty file (no data after gzip decompression); expected a header line with the columns "
                   f"{YJ_FIELDS}, then one line per record")


# ---------------------------------------------------------------------------- null tokens are no numbers
# A CSV reader's default null tokens (NA, NULL, nan, ...) would read such text in a count as a blank, then as a
# zero: only a blank field is a blank; any other text that is no finite number stops preparation, named as written.


def _with_line(path: Path, line: int, fields: dict[int, str]) -> Path:
    """Rewrites 1-based `line` of a Milan day file with the given 0-based fields replaced."""
    lines = path.read_text().splitlines(keepends=True)
    parts = lines[line - 1].rstrip("\n").split("\t")
    for k, v in fields.items():
        parts[k] = v
    lines[line - 1] = "\t".join(parts) + "\n"
    path.write_text("".join(lines))
    return path


def test_a_nan_milan_count_is_refused_not_read_as_zero(tmp_path, raw):
    for k in range(4):
        _milan_day(raw, k)
    assert _prepare(_config(), "milan", [raw], tmp_path / "ok", tmp_path)["dropped"] == {"duplicate_lines": 0}
    bad = _with_line(raw / "sms-call-internet-mi-2013-11-02.txt", 100, {7: "nan"})  # the case
    msg = _refused(_config(), "milan", [raw], tmp_path)
    assert msg == f"{bad}, line 100, column 'internet': expected a number, found 'nan'"


@pytest.mark.parametrize("field, token, expected", [
    (7, "NULL", "column 'internet': expected a number, found 'NULL'"),
    (7, "NA", "column 'internet': expected a number, found 'NA'"),
    (7, "-inf", "column 'internet': expected a number, found '-inf'"),
    (3, "N/A", "column 'sms_in': expected a number, found 'N/A'"),
    (0, "nan", "column 'square_id': expected an integer, found 'nan'"),  # the token, not "a blank field"
    (1, "NaN", "column 'time_interval_ms': expected an integer, found 'NaN'"),
    (2, "null", "column 'country_code': expected an integer, found 'null'"),
])
def test_a_null_token_in_any_milan_field_is_named(tmp_path, raw, field, token, expected):
    for k in (0, 2, 3):
        _milan_day(raw, k)
    day = _with_line(_milan_day(raw, 1), 7, {field: token})
    bad = raw / "sms-call-internet-mi-2013-11-02.txt.gz"
    bad.write_bytes(gzip.compress(day.read_bytes()))  # the published files are read packed as well
    day.unlink()
    msg = _refused(_config(), "milan", [raw], tmp_path)
    assert msg == f"{bad}, line 7, {expected}"


def test_a_blank_milan_square_id_is_still_a_blank_field(tmp_path, raw):
    for k in (0, 2, 3):
        _milan_day(raw, k)
    bad = _with_line(_milan_day(raw, 1), 3, {0: ""})
    msg = _refused(_config(), "milan", [raw], tmp_path)
    assert msg == f"{bad}, line 3, column 'square_id': expected a square id, found a blank field"


@pytest.mark.parametrize("token, column, expected", [
    ("nan", "x", "expected an integer, found 'nan'"),
    ("NA", "uid", "expected an integer, found 'NA'"),
    ("NULL", "d", "expected an integer, found 'NULL'"),
])
def test_a_null_token_in_a_yjmob_field_is_named(tmp_path, raw, token, column, expected):
    path = _yjmob(raw, [0, 1, 2, 3])
    lines = path.read_text().splitlines(keepends=True)
    fields = lines[41].rstrip("\n").split(",")  # line 42 of the file (after the header)
    fields["uid,d,t,x,y".split(",").index(column)] = token
    lines[41] = ",".join(fields) + "\n"
    path.write_text("".join(lines))
    msg = _refused(_config(), "yjmob", [path], tmp_path)
    assert msg == f"{path}, line 42, column {column!r}: {expected}"


@pytest.mark.parametrize("form", ["xlsx", "csv"])
@pytest.mark.parametrize("token", ["nan", "NULL", "inf"])
def test_a_null_token_in_a_shanghai_coordinate_is_named_not_a_missing_location(tmp_path, raw, form, token):
    rows = [tuple(str(v) if k in (4, 5) else v for k, v in enumerate(r))
            for r in _sessions(["2014-06-14", "2014-06-15", "2014-06-16", "2014-06-17"])]
    rows[30] = rows[30][:5] + (token,) + rows[30][6:]
    table = pl.DataFrame(rows, schema=SH_COLUMNS, orient="row")
    if form == "xlsx":
        bad = raw / "data_6.1~6.15.xlsx"
        _write_xlsx(bad, table)
        where = f"{bad}, sheet 'Sheet1', row 32"
    else:
        bad = raw / "export.csv"
        table.write_csv(bad)
        where = f"{bad}, row 32"
    msg = _refused(_config(), "shanghai", [bad], tmp_path)
    assert msg == f"{where}, column 'longitude': expected a number, found {token!r}"


def test_a_blank_shanghai_coordinate_is_still_a_counted_missing_location(tmp_path, raw):
    rows = _sessions(["2014-06-14", "2014-06-15", "2014-06-16", "2014-06-17"])
    rows[30] = rows[30][:5] + (None,) + rows[30][6:]
    meta = _prepare(_config(), "shanghai", [_workbook(raw / "data_6.1~6.15.xlsx", rows)], tmp_path / "out", tmp_path)
    assert meta["dropped"]["missing_location"] == 1


def test_a_nan_in_a_later_batch_is_located_on_its_line(tmp_path, monkeypatch):
    from prep import rawio

    monkeypatch.setattr(rawio, "BLOCK_BYTES", 256)  # many batches of a few lines each
    path = tmp_path / "counts.csv"
    path.write_text("id,count\n" + "".join(f"{i},{i}.5\n" for i in range(200)).replace("\n150,150.5\n",
                                                                                         "\n150,nan\n"))
    batches = rawio.iter_csv_batches(path, names=["id", "count"], types={"id": pa.int64(), "count": pa.float64()},
                                     has_header=True)
    with pytest.raises(PrepError) as err:
        list(batches)
    assert str(err.value) == f"{path}, line 152, column 'count': expected a number, found 'nan'"


# ---------------------------------------------------------------------------- split and eval days, at parse time


@pytest.mark.parametrize("dataset, key, value, expected", [
    ("milan", ("split", "train"), ["2013-11-01", "2013-11-31"],
     "config key datasets.milan.split.train[1]: expected an ISO date YYYY-MM-DD, found '2013-11-31'"),
    ("shanghai", ("split", "test"), ["2014-11-1", "2014-11-30"],  # the schema's pattern refuses it first
     "invalid configuration:\nconfig.yaml: key 'datasets.shanghai.split.test[0]' must be an ISO date in quotes, "
     "e.g. \"2013-11-01\"; found '2014-11-1'"),
    ("milan", ("split", "train"), ["2013-11-10", "2013-11-01"],
     "config key datasets.milan.split.train: expected [first, last] with first <= last, found "
     "['2013-11-10', '2013-11-01']"),
    ("milan", ("split", "test"), ["2013-11-05", "2013-11-12"],
     "config key datasets.milan.split.test[0]: expected a day after the last training day '2013-11-10' "
     "(datasets.milan.split.train[1]; the test segment follows the training segment without overlap), found "
     "'2013-11-05'"),
    ("shanghai", ("split", "test"), ["2014-10-31", "2014-11-30"],
     "config key datasets.shanghai.split.test[0]: expected a day after the last training day '2014-10-31' "
     "(datasets.shanghai.split.train[1]; the test segment follows the training segment without overlap), found "
     "'2014-10-31'"),
    ("yjmob", ("split", "test"), [50, 74],
     "config key datasets.yjmob.split.test[0]: expected a day after the last training day 55 "
     "(datasets.yjmob.split.train[1]; the test segment follows the training segment without overlap), found 50"),
    ("yjmob", ("split", "train"), [10, 3],
     "config key datasets.yjmob.split.train: expected [first, last] with first <= last, found [10, 3]"),
    ("yjmob", ("split", "test"), [56, 80],
     "config key datasets.yjmob.split.test[1]: expected a day number in 0..74 (datasets.yjmob.n_days: 75), "
     "found 80"),
    ("milan", ("eval_days", "id"), {"rule": "test_positions", "values": [0, 1, 12], "count": 3},
     "config key datasets.milan.eval_days.id.values[2]: expected a position in the test segment, 0..11 "
     "(12 days: 2013-12-21..2014-01-01), found 12"),
    ("yjmob", ("eval_days", "ood"), {"rule": "test_positions", "values": [19], "count": 1},
     "config key datasets.yjmob.eval_days.ood.values[0]: expected a position in the test segment, 0..18 "
     "(19 days: d56..d74), found 19"),
    ("milan", ("eval_days", "ood"), {"rule": "test_positions", "values": [], "count": 1},
     "config key datasets.milan.eval_days.ood.values: expected at least one position in the test segment, 0..11 "
     "(12 days: 2013-12-21..2014-01-01), found []"),
])
def test_bad_split_and_eval_days_are_refused_when_the_config_is_read(dataset, key, value, expected):
    config = copy.deepcopy(yaml.safe_load((ROOT / "config.yaml").read_text()))
    config["datasets"][dataset][key[0]][key[1]] = value
    with pytest.raises(ConfigError) as err:
        resolve(config)
    assert str(err.value) == expected


# ---------------------------------------------------------------------------- a slot without demand


class _Spy(StaticController):
    """Static, recording whether evaluation ever started it."""

    started = False

    def reset(self, ctx):
        type(self).started = True
        super().reset(ctx)

    def reset_batch(self, contexts):
        type(self).started = True
        super().reset_batch(contexts)


def test_an_evaluation_day_with_a_zero_demand_slot_is_refused(scenario):
    rng = np.random.default_rng(0)
    demand = rng.gamma(0.6, 1.0, size=(4, 144, 3, 3)).astype(np.float32) + 0.01
    demand[2, 5] = 0.0
    demand[2, 6] = 1e-12  # below the physics' demand threshold: no demand either
    days = [{"index": i, "label": lab, "split": "train" if i < 2 else "test", "weekday": 0, "weekend": False}
            for i, lab in enumerate(["2013-11-01", "2013-11-02", "2013-12-21", "2013-12-24"])]
    meta = {"dataset": "milan", "source": "raw", "days": days, "slots_per_day": 144,
            "eval_days": {"id": [2], "ood": [3]}, "grid": {"rows": 3, "cols": 3, "cell_m": 235.0}}
    tensor = DemandTensor(demand=demand, meta=meta, grid=GridSpec(rows=3, cols=3, cell_m=235.0))
    _Spy.started = False
    with pytest.raises(ValueError) as err:
        evaluate(tensor=tensor, controller=_Spy(name="static"), scenario=scenario, seed=0,
                 limits={"id": None, "ood": None}, profile="smoke", device="cpu", batch_days=True,
                 progress_interval_s=60.0)
    assert str(err.value) == ("milan: evaluation day 2013-12-21 (id) has zero total demand in the crop in slot(s) "
                              "[5, 6]; expected demand in every slot (the served ratio of an empty slot is "
                              "undefined, never scored as 1.0)")
    assert not _Spy.started  # refused before any controller ran: no day row exists to be written
