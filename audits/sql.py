"""An independent recomputation of the prepared data, in DuckDB SQL, straight from the raw files.

The other statistics checks rebuild the raw crop through the `prep` readers, so a reader bug (a slot boundary off by
one, UTC days for local days, a crop one column short) is made twice and agreed with twice. Here nothing of `prep`
runs: DuckDB reads Milan's daily TSV files (plain or gz) and YJMob's csv.gz with `read_csv`; Shanghai's workbooks are
read into Arrow by fastexcel (every cell as text) and registered as a relation (CSV exports through `read_csv`). From
those rows SQL alone computes, following docs/PROTOCOL.md §4 and the published formats:

* the crop: Milan's configured window of square ids (id = grid_row * full_cols + grid_col + 1); for Shanghai and
  YJMob the rows x cols window of the full grid with the most TRAINING-period records (session starts; records),
  ties to the smallest row, then column;
* the 10-minute slots in local time (Milan: the UTC epoch time converted to ``datasets.milan.timezone``; Shanghai's
  times are local; YJMob's 30-minute slot t is the 10-minute slots 3t..3t+2) and the day of each record;
* the demand per (day, slot, cell) in raw units: Milan, internet summed over country codes (exact duplicate lines of
  a file once); Shanghai, session starts (exact duplicate rows once, missing or 0/0 locations and sessions ending
  before they start dropped), trailing mean over the slot and the window_slots - 1 before it on a timeline that
  restarts where a day does not follow the previous one; YJMob, distinct uids per cell and 30-minute slot (masked
  records dropped), divided by 3;
* the training-segment percentile (linear interpolation, zeros of empty cells and slots included), the training
  mean of the normalized demand, kappa = reference training mean / training mean, and the all-days values.

The checks compare these with meta.json and every entry of demand.parquet, within the tolerances of
`audits.statistics`. The days come from the settings (`AuditContext.calendar`), never from the files under audit.
"""
from __future__ import annotations

import math
import shutil
import tempfile
import weakref
from dataclasses import dataclass
from pathlib import Path

import duckdb
import pyarrow as pa

from audits.context import AuditContext, AuditInputError
from audits.report import Check
from audits.statistics import RTOL, TENSOR_ATOL, TENSOR_RTOL, TOLERANCE, close

SLOTS = 144
"""10-minute slots per day."""
EARTH_RADIUS_M = 6_371_008.8
"""Mean Earth radius (IUGG) of the equirectangular projection the Shanghai grid is declared in."""
SHANGHAI_COLUMNS = {"month": "month", "date": "date", "start time": "start_time", "end time": "end_time",
                    "latitude": "latitude", "longitude": "longitude", "user id": "user_id"}
"""Shanghai's published columns (compared case-, space- and underscore-insensitively) and their names in SQL."""


@dataclass(frozen=True, kw_only=True)
class SqlStats:
    """One dataset recomputed in SQL. The per-entry demand stays in the connection as table ``values_<ds>``."""

    crop: dict  # {"first_row", "first_col", "rows", "cols"} (grid rows/cols; YJMob: row = y - 1, col = x - 1)
    train_records: int | None  # records (starts) in the window over the training days (None: fixed crop)
    p99: dict[str, float]  # {"train", "all"}
    mean_raw: dict[str, float]  # mean raw demand per cell and slot over {"train", "all"} days
    entries: dict[str, int]  # cell-slot values per day set, zeros included


class SqlRecomputation:
    """A DuckDB connection (in memory, one thread, spilling outside the audited tree) and the datasets it rebuilt."""

    def __init__(self, ctx: AuditContext):
        self.ctx = ctx
        self.tmp = tempfile.mkdtemp(prefix="audit-duckdb-")
        self.con = duckdb.connect(config={"threads": 1, "temp_directory": self.tmp,
                                          "autoinstall_known_extensions": False,
                                          "autoload_known_extensions": True})
        self.stats: dict[str, SqlStats] = {}
        self.failed: dict[str, AuditInputError] = {}
        self._cleanup = weakref.finalize(self, shutil.rmtree, self.tmp, True)

    def _q(self, query: str, params: dict | None = None) -> list[tuple]:
        """Runs one statement to completion; its rows."""
        return self.con.execute(query, params or {}).fetchall()

    def close(self) -> None:
        self.con.close()
        self._cleanup()

    # ---- the calendar, from the settings -------------------------------------------------------------
    def _calendar(self, ds: str) -> None:
        """Table ``cal_<ds>(pos, label, split, day_key, run)``: the configured days in tensor order; `run` numbers the
        stretches of consecutive days (the trailing window does not reach across a gap)."""
        cal = self.ctx.calendar(ds)
        numbered = cal[0][0].startswith("d")
        keys = [int(lab[1:]) if numbered else lab for lab, _ in cal]
        tbl = pa.table({"pos": list(range(len(cal))), "label": [lab for lab, _ in cal],
                        "split": [s for _, s in cal], "k": keys})
        self.con.register("cal_arrow", tbl)
        key = "k" if numbered else "CAST(k AS DATE)"
        self._q(f"""
            CREATE OR REPLACE TABLE cal_{ds} AS
            WITH c AS (SELECT pos, label, split, {key} AS day_key FROM cal_arrow),
            g AS (SELECT *, CASE WHEN day_key - lag(day_key) OVER (ORDER BY pos) = 1 THEN 0 ELSE 1 END AS new_run
                  FROM c)
            SELECT pos, label, split, day_key, sum(new_run) OVER (ORDER BY pos) AS run FROM g""")
        self.con.unregister("cal_arrow")

    # ---- raw rows to per-(day, slot, cell) demand ----------------------------------------------------
    def _milan(self, paths: list[Path]) -> tuple[dict, None]:
        cfg = self.ctx.section("milan")
        crop = {"first_row": int(cfg.crop.first_row), "first_col": int(cfg.crop.first_col),
                "rows": int(cfg.crop.rows), "cols": int(cfg.crop.cols)}
        names = ["square_id", "time_ms", "country_code", "sms_in", "sms_out", "call_in", "call_out", "internet"]
        self._q(f"""
            CREATE OR REPLACE TABLE values_milan AS
            WITH raw AS (
                SELECT *, (CAST(square_id AS BIGINT) - 1) // $full_cols - $first_row AS row,
                       (CAST(square_id AS BIGINT) - 1) % $full_cols - $first_col AS col
                FROM read_csv($files, delim = '\t', header = false, auto_detect = false, filename = true,
                              columns = {{{", ".join(f"'{n}': 'VARCHAR'" for n in names)}}})),
            line AS (  -- every field as text: a line is an exact duplicate of another only when all 8 are equal
                SELECT DISTINCT filename, row, col, {", ".join(names)} FROM raw
                WHERE row BETWEEN 0 AND $rows - 1 AND col BETWEEN 0 AND $cols - 1),
            cell AS (
                SELECT row, col, CAST(internet AS DOUBLE) AS internet,
                       (epoch_ms(CAST(time_ms AS BIGINT)) AT TIME ZONE 'UTC') AT TIME ZONE $tz AS local_time
                FROM line)
            SELECT c.pos, c.label, c.split, hour(local_time) * 6 + minute(local_time) // 10 AS slot, row, col,
                   coalesce(sum(internet), 0.0) AS value
            FROM cell JOIN cal_milan c ON c.day_key = CAST(local_time AS DATE)
            GROUP BY ALL""", {"files": [str(p) for p in paths], "full_cols": int(cfg.full_cols),
                              "first_row": crop["first_row"], "first_col": crop["first_col"],
                              "rows": crop["rows"], "cols": crop["cols"], "tz": str(cfg.timezone)})
        return crop, None

    def _densest(self, counts: str, height: int, width: int, rows: int, cols: int) -> tuple[int, int, int]:
        """(first_row, first_col, records) of the rows x cols window of `counts(row, col, n)` with the most records."""
        hit = self._q(f"""
            SELECT r - dr AS r0, c - dc AS c0, sum(n) AS total
            FROM {counts}, range($rows) AS a(dr), range($cols) AS b(dc)
            WHERE r - dr BETWEEN 0 AND $h - $rows AND c - dc BETWEEN 0 AND $w - $cols
            GROUP BY ALL ORDER BY total DESC, r0, c0 LIMIT 1""",
                      {"rows": rows, "cols": cols, "h": height, "w": width})
        return (0, 0, 0) if not hit else (int(hit[0][0]), int(hit[0][1]), int(hit[0][2]))

    def _yjmob(self, paths: list[Path]) -> tuple[dict, int]:
        cfg = self.ctx.section("yjmob")
        rows, cols, n = int(cfg.crop.rows), int(cfg.crop.cols), int(cfg.full_size)
        self._q("""
            CREATE OR REPLACE TEMP TABLE yjmob_records AS
            SELECT r.uid, c.pos, c.label, c.split, r.t, r.x, r.y
            FROM read_csv($files, header = true, auto_detect = false,
                          columns = {'uid': 'BIGINT', 'd': 'BIGINT', 't': 'BIGINT', 'x': 'BIGINT', 'y': 'BIGINT'}) r
            JOIN cal_yjmob c ON c.day_key = r.d
            WHERE NOT (r.x = $masked AND r.y = $masked)""",
                         {"files": [str(p) for p in paths], "masked": int(cfg.masked_value)})
        self._q("""CREATE OR REPLACE TEMP TABLE yjmob_train_cells AS
                            SELECT y - 1 AS r, x - 1 AS c, count(*) AS n FROM yjmob_records
                            WHERE split = 'train' GROUP BY ALL""")
        r0, c0, total = self._densest("yjmob_train_cells", n, n, rows, cols)
        per = SLOTS // int(cfg.raw_slots_per_day)
        self._q("""
            CREATE OR REPLACE TABLE values_yjmob AS
            WITH users AS (
                SELECT pos, label, split, t, y - 1 - $r0 AS row, x - 1 - $c0 AS col, count(DISTINCT uid) AS n
                FROM yjmob_records
                WHERE y - 1 BETWEEN $r0 AND $r0 + $rows - 1 AND x - 1 BETWEEN $c0 AND $c0 + $cols - 1
                GROUP BY ALL)
            SELECT pos, label, split, t * $per + k AS slot, row, col, n / $per AS value
            FROM users, range($per) AS s(k)""", {"r0": r0, "c0": c0, "rows": rows, "cols": cols, "per": per})
        return {"first_row": r0, "first_col": c0, "rows": rows, "cols": cols}, total

    def _shanghai_rows(self, paths: list[Path]) -> pa.Table:
        """Every row of every workbook sheet (fastexcel, all cells as text) or CSV export, the published columns
        renamed to their SQL names."""
        import fastexcel

        def norm(name: str) -> str:
            return " ".join(str(name).strip().lower().replace("_", " ").split())

        parts = []
        for path in paths:
            if path.suffix.lower() in (".xlsx", ".xlsm", ".xls"):
                try:
                    book = fastexcel.read_excel(str(path))
                    sheets = [(name, book.load_sheet(name, dtypes="string").to_arrow()) for name in book.sheet_names]
                except Exception as exc:  # fastexcel raises its own exception types
                    raise AuditInputError(f"{self.ctx.rel(path)}: cannot read as an Excel workbook ({exc})") from exc
            else:
                sheets = [("", self.con.sql("SELECT * FROM read_csv($f, header = true, all_varchar = true)",
                                                params={"f": str(path)}).to_arrow_table())]
            for sheet, tbl in sheets:
                if tbl.num_rows == 0:
                    continue
                found = {norm(c): c for c in tbl.column_names}
                missing = [c for c in SHANGHAI_COLUMNS if c not in found]
                if missing:
                    raise AuditInputError(f"{self.ctx.rel(path)}{f', sheet {sheet!r}' if sheet else ''}: missing "
                                          f"column(s) {missing}; found {tbl.column_names}")
                parts.append(pa.table({sql: tbl[found[c]].cast(pa.string()) for c, sql in SHANGHAI_COLUMNS.items()}))
        if not parts:
            raise AuditInputError(f"shanghai: no rows in {[self.ctx.rel(p) for p in paths][:3]}")
        return pa.concat_tables(parts)

    def _shanghai(self, paths: list[Path]) -> tuple[dict, int]:
        cfg = self.ctx.section("shanghai")
        m_lat = EARTH_RADIUS_M * math.pi / 180.0
        m_lon = m_lat * math.cos(math.radians((cfg.lat_min + cfg.lat_max) / 2))
        height = math.ceil((cfg.lat_max - cfg.lat_min) * m_lat / cfg.cell_m)
        width = math.ceil((cfg.lon_max - cfg.lon_min) * m_lon / cfg.cell_m)
        self.con.register("shanghai_arrow", self._shanghai_rows(paths))
        fmt = "['%Y-%m-%d %H:%M:%S', '%Y-%m-%d %H:%M:%S.%f']"
        self._q(f"""
            CREATE OR REPLACE TEMP TABLE shanghai_starts AS
            WITH parsed AS (  -- one source per session: rows equal in every column (times and places parsed) once
                SELECT DISTINCT trim(month) AS month, trim(date) AS date,
                       try_strptime(trim(start_time), {fmt}) AS t0, try_strptime(trim(end_time), {fmt}) AS t1,
                       try_cast(trim(latitude) AS DOUBLE) AS lat, try_cast(trim(longitude) AS DOUBLE) AS lon,
                       trim(user_id) AS uid
                FROM shanghai_arrow),
            kept AS (
                SELECT * FROM parsed
                WHERE lat IS NOT NULL AND lon IS NOT NULL AND NOT (lat = 0 AND lon = 0)
                  AND NOT coalesce(t1 < t0, false)
                  AND lat BETWEEN $lat_min AND $lat_max AND lon BETWEEN $lon_min AND $lon_max)
            SELECT c.pos, c.label, c.split, c.run, hour(t0) * 6 + minute(t0) // 10 AS slot,
                   least(CAST(floor((lat - $lat_min) * $m_lat / $cell) AS BIGINT), $h - 1) AS r,
                   least(CAST(floor((lon - $lon_min) * $m_lon / $cell) AS BIGINT), $w - 1) AS c,
                   count(*) AS n
            FROM kept JOIN cal_shanghai c ON c.day_key = CAST(t0 AS DATE)
            GROUP BY ALL""", {"lat_min": cfg.lat_min, "lat_max": cfg.lat_max, "lon_min": cfg.lon_min,
                              "lon_max": cfg.lon_max, "m_lat": m_lat, "m_lon": m_lon, "cell": float(cfg.cell_m),
                              "h": height, "w": width})
        self.con.unregister("shanghai_arrow")
        self._q("""CREATE OR REPLACE TEMP TABLE shanghai_train_cells AS
                            SELECT r, c, sum(n) AS n FROM shanghai_starts WHERE split = 'train' GROUP BY ALL""")
        rows, cols = int(cfg.crop.rows), int(cfg.crop.cols)
        r0, c0, total = self._densest("shanghai_train_cells", height, width, rows, cols)
        # Trailing mean: the starts of slot s reach slots s..s+w-1 of the same run; the mean divides by the slots
        # the window holds there (fewer at the start of a run).
        self._q("""
            CREATE OR REPLACE TABLE values_shanghai AS
            WITH runs AS (SELECT run, min(pos) AS first, max(pos) AS last FROM cal_shanghai GROUP BY run),
            timed AS (
                SELECT s.run, (s.pos - runs.first) * 144 + s.slot AS t, runs.last - runs.first AS span,
                       runs.first, s.r - $r0 AS row, s.c - $c0 AS col, s.n
                FROM shanghai_starts s JOIN runs USING (run)
                WHERE s.r BETWEEN $r0 AND $r0 + $rows - 1 AND s.c BETWEEN $c0 AND $c0 + $cols - 1),
            reach AS (
                SELECT first + tt // 144 AS pos, tt % 144 AS slot, row, col, sum(n) / least($win, tt + 1) AS value
                FROM (SELECT first, t + k AS tt, span, row, col, n FROM timed, range($win) AS w(k))
                WHERE tt // 144 <= span
                GROUP BY first, tt, row, col)
            SELECT c.pos, c.label, c.split, slot, row, col, value FROM reach JOIN cal_shanghai c USING (pos)""",
                         {"r0": r0, "c0": c0, "rows": rows, "cols": cols, "win": int(cfg.window_slots)})
        return {"first_row": r0, "first_col": c0, "rows": rows, "cols": cols}, total

    # ---- statistics -----------------------------------------------------------------------------------
    def dataset(self, ds: str) -> SqlStats:
        """The dataset rebuilt from its raw files (the files meta.json records, checked by SHA-256)."""
        if ds in self.stats:
            return self.stats[ds]
        if ds in self.failed:
            raise self.failed[ds]
        build = {"milan": self._milan, "yjmob": self._yjmob, "shanghai": self._shanghai}.get(ds)
        if build is None:
            raise AuditInputError(f"{ds}: no SQL recomputation for this dataset")
        paths = self.ctx.raw_paths(ds)
        self._calendar(ds)
        try:
            crop, records = build(paths)
        except duckdb.Error as exc:
            names = [self.ctx.rel(p) for p in paths][:3]
            self.failed[ds] = AuditInputError(f"{ds}: the SQL recomputation from {names} failed ({exc})")
            raise self.failed[ds] from exc
        except AuditInputError as exc:
            self.failed[ds] = exc
            raise
        cells = crop["rows"] * crop["cols"] * SLOTS
        entries = {s: int(n) * cells for s, n in self._q(
            f"SELECT 'train', count(*) FILTER (split = 'train') FROM cal_{ds} UNION ALL "
            f"SELECT 'all', count(*) FROM cal_{ds}")}
        p99, mean = {}, {}
        for which, where in (("train", "split = 'train'"), ("all", "true")):
            p99[which], mean[which] = self._q(f"""
                WITH v AS (SELECT value FROM values_{ds} WHERE {where})
                SELECT (SELECT quantile_cont(value, $q) FROM (
                            SELECT value FROM v UNION ALL  -- the cells and slots without demand
                            SELECT 0.0 FROM range($n - (SELECT count(*) FROM v)))),
                       (SELECT coalesce(sum(value), 0.0) FROM v) / $n""",
                {"q": self.ctx.percentile / 100.0, "n": entries[which]})[0]
        out = SqlStats(crop=crop, train_records=records, p99=p99, mean_raw=mean, entries=entries)
        self.stats[ds] = out
        return out

    def normalizer(self, ds: str) -> dict[str, float]:
        """p99, training mean of the normalized demand, kappa and the reference mean, as SQL gives them."""
        mine, ref = self.dataset(ds), self.dataset(self.ctx.kappa_reference)
        ref_mean = ref.mean_raw["train"] / ref.p99["train"]
        train_mean = mine.mean_raw["train"] / mine.p99["train"]
        return {"p99": mine.p99["train"], "p99_all_days": mine.p99["all"], "train_mean_normalized": train_mean,
                "kappa_reference_mean": ref_mean, "kappa": 1.0 if ds == self.ctx.kappa_reference else
                ref_mean / train_mean}

    def compare_tensor(self, ds: str, tensor: Path, meta: dict, scale: float) -> dict:
        """Every entry of demand.parquet against the SQL demand x scale (entries absent from either side are 0).

        Returns:
            {"entries", "entries_off", "max_abs_error", "first": (label, slot, row, col, stored, expected) | None}.
        """
        days = pa.table({"day": [int(d["index"]) for d in meta["days"]],
                         "label": [str(d["label"]) for d in meta["days"]]})
        self.con.register("meta_days", days)
        cmp = f"""
            WITH stored AS (SELECT m.label, p.slot, p.row, p.col, CAST(p.demand AS DOUBLE) AS v
                            FROM read_parquet($tensor) p LEFT JOIN meta_days m USING (day)),
            expected AS (SELECT label, slot, row, col, value * $scale AS v FROM values_{ds}),
            paired AS (SELECT label, slot, row, col, coalesce(s.v, 0.0) AS stored, coalesce(e.v, 0.0) AS expected
                     FROM stored s FULL JOIN expected e USING (label, slot, row, col))
            SELECT *, abs(stored - expected) AS err, abs(stored - expected) > $atol + $rtol * abs(expected) AS bad
            FROM paired"""
        args = {"tensor": str(tensor), "scale": scale, "atol": TENSOR_ATOL, "rtol": TENSOR_RTOL}
        try:
            n, off, worst = self._q(f"SELECT count(*), count(*) FILTER (bad), coalesce(max(err), 0) FROM ({cmp})",
                                    args)[0]
            first = self._q(f"""SELECT label, slot, row, col, stored, expected FROM ({cmp}) c
                                LEFT JOIN cal_{ds} USING (label) WHERE bad
                                ORDER BY pos NULLS FIRST, slot, row, col LIMIT 1""", args)
        except duckdb.Error as exc:
            raise AuditInputError(f"{self.ctx.rel(tensor)}: cannot be compared in SQL ({exc})") from exc
        finally:
            self.con.unregister("meta_days")
        return {"entries": int(n), "entries_off": int(off), "max_abs_error": float(worst),
                "first": first[0] if first else None}


def recomputation(ctx: AuditContext) -> SqlRecomputation:
    """The connection and datasets the SQL checks share (cached on ctx; closed by `close_recomputation`)."""
    if "sql" not in ctx.cache:
        ctx.cache["sql"] = SqlRecomputation(ctx)
    return ctx.cache["sql"]


def close_recomputation(ctx: AuditContext) -> None:
    sql = ctx.cache.pop("sql", None)
    if sql is not None:
        sql.close()


def check_sql_crop(ctx: AuditContext) -> Check:
    """The crop recorded in meta.json is the one SQL finds from the raw files."""
    chk = Check(id="statistics.sql_crop", family="statistics",
                claim="Each dataset's crop in meta.json is the one DuckDB SQL computes from the raw files alone: the "
                      "configured window (Milan) or the window of the full grid with the most TRAINING-period records "
                      "(Shanghai, YJMob).")
    sql = recomputation(ctx)
    for ds in ctx.datasets:
        try:
            got, meta = sql.dataset(ds), ctx.meta(ds)
        except AuditInputError as exc:
            chk.fail(f"{exc} — the crop cannot be recomputed in SQL")
            continue
        crop = meta.get("crop", {})
        if ds == "yjmob":
            stored = {"first_row": crop.get("first_y", 0) - 1, "first_col": crop.get("first_x", 0) - 1}
        else:
            stored = {k: crop.get(k) for k in ("first_row", "first_col")}
        stored.update(rows=crop.get("rows"), cols=crop.get("cols"))
        if stored != got.crop:
            chk.fail(f"{ctx.rel(ctx.meta_path(ds))}: crop (grid row, col, rows, cols) "
                     f"{tuple(stored.values())}, SQL over the raw files gives {tuple(got.crop.values())}"
                     + (f" ({got.train_records} training records in the window)" if got.train_records is not None
                        else " (datasets.milan.crop)"))
        chk.evidence[ds] = {"stored": stored, "sql": got.crop, "train_records_in_window": got.train_records}
    return chk


def check_sql_normalizer(ctx: AuditContext) -> Check:
    """p99, the training mean and kappa in meta.json equal the SQL recomputation from the raw files."""
    chk = Check(id="statistics.sql_normalizer", family="statistics", tolerance=f"relative {RTOL:g}",
                claim="p99 (training and all days), the training mean of the normalized demand, kappa and the "
                      "reference mean in meta.json equal the values DuckDB SQL computes from the raw files alone.")
    sql = recomputation(ctx)
    for ds in ctx.datasets:
        try:
            want, meta = sql.normalizer(ds), ctx.meta(ds)
        except AuditInputError as exc:
            chk.fail(f"{exc} — the normalizer cannot be recomputed in SQL")
            continue
        for key, value in want.items():
            if not close(meta.get(key), value):
                chk.fail(f"{ctx.rel(ctx.meta_path(ds))}: {key} = {meta.get(key)!r}, SQL over the raw files gives "
                         f"{value:.9g}")
        chk.evidence[ds] = {k: {"stored": meta.get(k), "sql": v} for k, v in want.items()}
    return chk


def check_sql_tensor(ctx: AuditContext) -> Check:
    """Every entry of demand.parquet equals the SQL demand of its day, slot and cell / p99 x kappa."""
    chk = Check(id="statistics.sql_tensor", family="statistics", tolerance=TOLERANCE,
                claim="Every entry of demand.parquet equals the demand DuckDB SQL computes from the raw files alone "
                      "for its local day, 10-minute slot and cell, divided by the SQL training p99 and times the SQL "
                      "kappa.")
    sql = recomputation(ctx)
    try:
        for ds in ctx.datasets:
            try:
                norm, meta = sql.normalizer(ds), ctx.meta(ds)
                tensor = ctx.ledger.track(ctx.tensor_path(ds))
                got = sql.compare_tensor(ds, tensor, meta, norm["kappa"] / norm["p99"])
            except (AuditInputError, FileNotFoundError) as exc:
                chk.fail(f"{exc} — the tensor cannot be recomputed in SQL")
                continue
            if got["entries_off"]:
                label, slot, row, col, stored, want = got["first"]
                chk.fail(f"{ctx.rel(ctx.tensor_path(ds))}: {got['entries_off']} of {got['entries']} entries differ "
                         f"from the SQL demand of their local day, slot and cell (first: day {label}, slot {slot}, "
                         f"row {row}, col {col}: stored {stored:.7g}, SQL {want:.7g})")
            chk.evidence[ds] = {k: v for k, v in got.items() if k != "first"}
    finally:
        close_recomputation(ctx)
    return chk
