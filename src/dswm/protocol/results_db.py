"""Every per-day result one SQL query away: the DuckDB views the tables are computed from.

``results/results.duckdb`` (written by the tables rule, :func:`write_database`) holds two views and no data:

* ``days``: every ``results/<dataset>/<method>/seed<seed>/days.parquet`` of the run, read in place
  (``read_parquet`` over the files, ``union_by_name``): one row per evaluated day with its dataset, method, seed,
  split, metrics and hashes, as the result files hold them.
* ``summary``: :data:`SUMMARY_SQL` over ``days``: per (dataset, method), the mean and sample standard deviation over
  seeds of each seed's mean day score, per split, for the served ratio and the metrics of :data:`METRICS`.

The tables (``dswm.protocol.tables``) run the very same :data:`SUMMARY_SQL` over the same files, so the view and the
tables cannot disagree. The views store the paths of the result files as given: relative to the workflow's working
directory, so the database works wherever the tree is moved or copied, opened from the tree's root.
"""
from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import duckdb
import polars as pl

from prep.atomic import atomic_path

METRICS = {"": "sr_mean", "energy_": "energy_kj_per_slot", "efficiency_": "energy_efficiency", "jain_": "jain"}
"""{summary column prefix: days.parquet column}: the served ratio, then the metrics of Table III."""
SPLITS = {"weekday": "id", "holiday": "ood"}
"""{summary column word: days.parquet split}."""


def _summary_sql() -> str:
    per_seed = ", ".join(f"avg({col} ORDER BY day) AS {col}" for col in METRICS.values())
    cols = []
    for pre, col in METRICS.items():
        for word, split in SPLITS.items():
            cols.append(f"avg({col} ORDER BY seed) FILTER (split = '{split}') AS {pre}{word}_mean")
            cols.append(f"coalesce(stddev_samp({col} ORDER BY seed) FILTER (split = '{split}'), 0.0) "
                        f"AS {pre}{word}_std")
    return (f"WITH per_seed AS (SELECT dataset, method, seed, split, {per_seed} FROM days "
            f"GROUP BY dataset, method, seed, split)\n"
            f"SELECT dataset, method,\n       {(',' + chr(10) + '       ').join(cols)},\n"
            f"       count(DISTINCT seed) FILTER (split = 'id') AS n_seeds,\n"
            f"       count(DISTINCT seed) FILTER (split = 'ood') AS holiday_seeds\n"
            f"FROM per_seed GROUP BY dataset, method ORDER BY dataset, method")


SUMMARY_SQL = _summary_sql()
"""Per (dataset, method) over the relation ``days``: a seed's score on a split is the mean of its days' value; the
summary gives the mean and the sample standard deviation (0 with a single seed) of those scores over seeds, for each
metric of :data:`METRICS` (``<prefix><weekday|holiday>_<mean|std>``), and the seeds of each split (``n_seeds`` the
weekday ones, ``holiday_seeds``). A seed whose days lack a metric (null) gives a null mean."""


def days_sql(paths: Iterable[str | Path]) -> str:
    """The SELECT of the ``days`` view over the given result files (their paths as given, in order)."""
    files = ", ".join("'" + Path(p).as_posix().replace("'", "''") + "'" for p in paths)
    return f"SELECT * FROM read_parquet([{files}], union_by_name = true)"


def connect(paths: Iterable[str | Path], database: str | Path = ":memory:") -> duckdb.DuckDBPyConnection:
    """A connection (one thread: the sums run in one order, so every number is reproducible) with the views
    ``days`` over `paths` and ``summary``."""
    paths = list(paths)
    if not paths:
        raise ValueError("no result files given; expected results/{dataset}/{method}/seed{seed}/days.parquet")
    con = duckdb.connect(str(database), config={"threads": 1, "autoinstall_known_extensions": False})
    con.execute(f"CREATE VIEW days AS {days_sql(paths)}").fetchall()
    con.execute(f"CREATE VIEW summary AS {SUMMARY_SQL}").fetchall()
    return con


def summary(con: duckdb.DuckDBPyConnection) -> pl.DataFrame:
    """The ``summary`` view as a DataFrame.

    Raises:
        ValueError: a (dataset, method) whose weekday and holiday splits cover different seeds.
    """
    out = con.sql("SELECT * FROM summary").pl()
    bad = out.filter(pl.col("n_seeds") != pl.col("holiday_seeds"))
    if bad.height:
        row = bad.row(0, named=True)
        raise ValueError(f"results of {row['dataset']}/{row['method']}: weekday and holiday splits cover different "
                         f"seeds ({row['n_seeds']} vs {row['holiday_seeds']}); expected both splits for every seed")
    return out.drop("holiday_seeds")


def write_database(target: str | Path, paths: Iterable[str | Path]) -> None:
    """Writes the database of views (no copy of the data) atomically: built in a temp file, then renamed.

    Args:
        target: results/results.duckdb.
        paths: every days.parquet of the run, relative to the working directory the database is opened from.
    """
    with atomic_path(target) as tmp:
        Path(tmp).unlink()  # DuckDB creates its own file
        con = connect(paths, tmp)
        con.execute("CHECKPOINT").fetchall()
        con.close()
