"""The audit's independent recomputation in DuckDB SQL (audits.sql): it agrees with a clean tree without running a
`prep` reader, and it sees the reader bugs the reader-based checks agree with.

Each mutation patches one line of the Milan reader (`prep.milan.build`) the way a real slip would, prepares the tree
again with it and audits with it still in place: the reader-based statistics checks rebuild the raw crop with the
same reader and pass, the SQL checks fail and name the file and the first entry that differs.
"""
from __future__ import annotations

import inspect
import shutil
import textwrap
from pathlib import Path

import numpy as np
import polars as pl
import pytest

from audit_fixtures import clean, one_torch_thread, prepare, tree  # noqa: F401 (fixtures)
from audits import crop, sql, statistics
from audits.context import AuditContext, label_range
from test_audit import milan_train_p99_from_raw

READER_CHECKS = (statistics.check_p99, statistics.check_kappa, statistics.check_tensor,
                 statistics.check_not_all_days, crop.check_crop)
SQL_CHECKS = (sql.check_sql_crop, sql.check_sql_normalizer, sql.check_sql_tensor)


def _run(root: Path, settings, checks) -> dict:
    ctx = AuditContext(root=root, settings=settings)
    return {c.id: c for c in (fn(ctx) for fn in checks)}


def test_sql_checks_pass_on_the_clean_tree_without_any_prep_reader(clean, monkeypatch):
    root, settings = clean
    import prep.milan
    import prep.rawio
    import prep.shanghai
    import prep.yjmob

    def refuse(*args, **kwargs):
        raise AssertionError("a prep reader ran")

    for module, name in ((prep.milan, "build"), (prep.milan, "read_raw"), (prep.yjmob, "build"),
                         (prep.yjmob, "iter_records"), (prep.shanghai, "build"), (prep.shanghai, "iter_sessions"),
                         (prep.rawio, "iter_csv_batches")):
        monkeypatch.setattr(module, name, refuse)
    checks = _run(root, settings, SQL_CHECKS)
    assert all(c.passed for c in checks.values()), {k: c.failures for k, c in checks.items()}
    norm = checks["statistics.sql_normalizer"].evidence
    assert norm["milan"]["p99"]["sql"] == pytest.approx(milan_train_p99_from_raw(root), rel=1e-12)
    assert norm["milan"]["kappa"]["sql"] == 1.0 and norm["yjmob"]["kappa"]["sql"] != pytest.approx(1.0, rel=0.01)
    tensor = checks["statistics.sql_tensor"].evidence
    assert tensor["milan"]["entries_off"] == 0 and tensor["milan"]["entries"] == 10 * 144 * 25  # every entry > 0
    crops = checks["statistics.sql_crop"].evidence
    assert crops["milan"]["sql"] == {"first_row": 40, "first_col": 40, "rows": 5, "cols": 5}
    assert crops["yjmob"]["sql"] == crops["yjmob"]["stored"] and crops["yjmob"]["train_records_in_window"] > 0


def mutated_build(old: str, new: str):
    """`prep.milan.build` with one piece of its source replaced (it must occur exactly once)."""
    import prep.milan

    src = textwrap.dedent(inspect.getsource(prep.milan.build))
    assert src.count(old) == 1, old
    namespace = dict(vars(prep.milan))
    exec(compile(src.replace(old, new), prep.milan.__file__, "exec"), namespace)
    return namespace["build"]


MUTATIONS = {
    # every slot one later (the last slot of a day wraps to its first)
    "slot_shift": ("local.dt.minute().cast(pl.Int64) // 10).to_numpy()",
                   "local.dt.minute().cast(pl.Int64) // 10 + 1).to_numpy() % SLOTS_PER_DAY"),
    # the day of a record taken from its UTC time, not its local (Europe/Rome) time
    "utc_days": ("epoch_day = local.dt.date()", "epoch_day = local.dt.convert_time_zone('UTC').dt.date()"),
    # the crop's squares one column short (meta.json still records the configured 5 columns)
    "crop_column": ("np.arange(crop.cols), indexing", "np.arange(crop.cols - 1), indexing"),
}




@pytest.mark.parametrize("mutation, first, p99_moves", [
    ("slot_shift", "day 2013-11-01, slot 0, row 0, col 0", False),  # the same values, each in the wrong slot
    ("utc_days", "day 2013-11-01, slot 0, row 0, col 0", False),  # night hours moved: the training total stays
    ("crop_column", "day 2013-11-01, slot 0, row 0, col 0", True),  # p99 moves: every entry differs
])
def test_a_reader_bug_passes_the_reader_checks_and_fails_the_sql_checks(tree, monkeypatch, mutation, first, p99_moves):
    root, settings = tree
    import prep.milan

    monkeypatch.setattr(prep.milan, "build", mutated_build(*MUTATIONS[mutation]))
    prepare(settings, root)  # the whole tree prepared by the faulty reader, kappa included
    reader = _run(root, settings, READER_CHECKS)
    assert all(c.passed for c in reader.values()), {k: c.failures for k, c in reader.items()}
    checks = _run(root, settings, SQL_CHECKS)
    msg, *others = checks["statistics.sql_tensor"].failures
    assert msg.startswith("results/data/milan/demand.parquet: ") and f"(first: {first}: stored " in msg, msg
    assert "entries differ from the SQL demand of their local day, slot and cell" in msg
    assert checks["statistics.sql_crop"].passed  # the recorded crop is still the configured one
    norm = checks["statistics.sql_normalizer"].failures
    if p99_moves:  # Milan's training mean moves too, and with it kappa and every YJMob entry
        assert [m.split(" = ")[0] for m in norm] == [
            "results/data/milan/meta.json: p99", "results/data/milan/meta.json: p99_all_days",
            "results/data/milan/meta.json: train_mean_normalized", "results/data/milan/meta.json: kappa_reference_mean",
            "results/data/yjmob/meta.json: kappa_reference_mean", "results/data/yjmob/meta.json: kappa"], norm
        assert [m.split(":")[0] for m in others] == ["results/data/yjmob/demand.parquet"]
    else:  # only the entries tell
        assert norm == [] and others == []


def test_the_sql_checks_name_a_stored_entry_that_differs(tree):
    root, settings = tree
    path = root / "results/data/yjmob/demand.parquet"
    df = pl.read_parquet(path)
    df = df.with_columns(pl.when(pl.int_range(pl.len()) == 7).then(pl.col("demand") * 1.01)
                         .otherwise(pl.col("demand")).alias("demand"))
    df.write_parquet(path)
    row = df.row(7, named=True)
    label = f"d{row['day']}"  # the fixture's YJMob days are d0..d15 in order
    [msg] = _run(root, settings, SQL_CHECKS)["statistics.sql_tensor"].failures
    assert msg.startswith(f"results/data/yjmob/demand.parquet: 1 of ") and \
        f"(first: day {label}, slot {row['slot']}, row {row['row']}, col {row['col']}: stored " in msg, msg


class _Ctx:
    """The part of an AuditContext the SQL recomputation uses, for one Shanghai section (no tree)."""

    def __init__(self, cfg, paths):
        self.cfg, self.paths = cfg, paths
        self.percentile, self.kappa_reference = 99.0, "shanghai"

    def calendar(self, ds):
        return [(lab, s) for s in ("train", "test") for lab in label_range(*getattr(self.cfg.split, s))]

    def section(self, ds):
        return self.cfg

    def raw_paths(self, ds):
        return self.paths

    def rel(self, path):
        return str(path)


def test_shanghai_in_sql_equals_the_reader_on_demo_workbooks(tmp_path):
    """Shanghai's workbooks through fastexcel and SQL (dirt dropped, a workbook present twice and one also as a CSV
    export counted once, the trailing window restarting at the gap between the segments) give the reader's tensor
    and crop."""
    from prep import shanghai
    from prep.demo.shanghai import generate
    from test_prep_shanghai import _config

    cfg = _config(train=("2014-06-01", "2014-06-12"), test=("2014-06-14", "2014-06-20"))
    files = generate(cfg, tmp_path)
    twice = tmp_path / "copy of data_6.1~6.15.xlsx"
    shutil.copy(files[0], twice)
    export = tmp_path / "data_6.16~6.30.csv"  # the second workbook once more, as a CSV export
    pl.read_excel(files[1]).write_csv(export)
    paths = [*files, twice, export]
    raw = shanghai.build(cfg, paths)
    assert raw.dropped["duplicate_rows"] > pl.read_excel(files[0]).height and raw.dropped["missing_location"] > 0
    rec = sql.SqlRecomputation(_Ctx(cfg, paths))
    try:
        got = rec.dataset("shanghai")
        dense = np.zeros_like(raw.values)
        for pos, slot, row, col, value in rec.con.execute(
                "SELECT pos, slot, row, col, value FROM values_shanghai").fetchall():
            dense[pos, slot, row, col] = value
    finally:
        rec.close()
    assert (got.crop["first_row"], got.crop["first_col"]) == (raw.crop["first_row"], raw.crop["first_col"])
    assert got.train_records == raw.crop["train_starts"]
    np.testing.assert_allclose(dense, raw.values, rtol=1e-12, atol=0)
    assert dense[12, :3].sum() > 0  # the first test day's first slots, whose window stops at the gap
    assert got.p99["train"] == pytest.approx(np.percentile(raw.values[:12].ravel(), 99), rel=1e-12)
