"""Protocol family, part 3: the sample-efficiency probe's numbers stay out of the tables.

* `check_probes_out_of_tables`: every probe file (`results/probes/<dataset>/<method>/seed<seed>/probe.parquet`,
  `dswm.protocol.probe`) lies outside the tables' sources and carries its marks, and no table source
  (`results/<dataset>/<method>/seed<seed>/days.parquet` of every job of the profile) holds a probe row: a probe
  column, the probe split, or a served ratio equal to a probe number.

A probe number is a snapshot's value on the probe day that is not the evaluation's own value: each probe row records
``evaluated_sr_mean``, what the probed job's evaluation scored on that day when the probe ran. The last snapshot is
the trained model, so its value usually is the evaluation's number (the same model, day, environment and seed; a
planner whose random stream depends on the days stepped together may differ), and so may a checkpoint's that
scores the same; a row equal to its recorded evaluation value is the table's own number and is left out of the
comparison (the report lists such rows). Values are compared exactly: a copied number is the same float.
"""
from __future__ import annotations

from pathlib import Path

import polars as pl

from audits.context import AuditContext
from audits.protocol import _results
from audits.report import Check


PROBES_LEFT_OUT = ("the probe files are not read by this audit, whose inputs are the tables' sources alone: the "
                   "probe audit (results/audit/probes.json, the `audit_probes` rule, run by `figures` and `audit`) "
                   "compares their numbers with these sources")
"""The evidence note of the check in an audit that leaves the probe files out (``AuditContext.read_probes``)."""


def probe_files(ctx: AuditContext) -> list[Path]:
    """Every probe file under results/probes/ (the probe rule's outputs; none in a run without probes, and none
    read by an audit that leaves them out: ``ctx.read_probes``)."""
    from dswm.protocol.probe import PROBE_DIR, PROBE_FILE

    base = ctx.root / PROBE_DIR
    return sorted(base.rglob(PROBE_FILE)) if base.is_dir() and ctx.read_probes else []


def _read(ctx: AuditContext, chk: Check, path: Path) -> pl.DataFrame | None:
    try:
        return pl.read_parquet(ctx.ledger.track(path))
    except (OSError, pl.exceptions.PolarsError) as exc:
        chk.fail(f"{ctx.rel(path)}: unreadable probe file ({exc})")
        return None


def _probe_rows(ctx: AuditContext, chk: Check, path: Path, df: pl.DataFrame) -> list[dict]:
    """The rows of one probe file, after checking its marks; each with ``where`` (the probe file) and ``own``
    (True: its value is the one the probed job's evaluation recorded on that day)."""
    from dswm.protocol.probe import PROBE_COLUMNS, PROBE_SPLIT

    where = ctx.rel(path)
    need = ["dataset", "method", "seed", "day", "label", "split", "sr_mean", *PROBE_COLUMNS]
    missing = [c for c in need if c not in df.columns]
    if missing:
        chk.fail(f"{where}: a probe file without the column(s) {missing} — its rows cannot be told from a result "
                 f"file's; re-run its probe job")
        return []
    unmarked = df.filter((pl.col("split") != PROBE_SPLIT) | ~pl.col("probe"))
    if unmarked.height:
        chk.fail(f"{where}: {unmarked.height} row(s) without the probe marks (split {PROBE_SPLIT!r}, probe = true); "
                 f"re-run its probe job")
    return [{**r, "where": where, "own": r["evaluated_sr_mean"] is not None and r["sr_mean"] == r["evaluated_sr_mean"]}
            for r in df.iter_rows(named=True)]


def check_probes_out_of_tables(ctx: AuditContext) -> Check:
    """No probe number of the sample-efficiency probe is in a table's source."""
    from dswm.protocol.probe import PROBE_COLUMNS, PROBE_FILE, PROBE_RECORD_FILE, PROBE_SPLIT

    chk = Check(id="protocol.probes_out_of_tables", family="protocol",
                claim="Every probe file of the sample-efficiency probe lies under results/probes/, outside the tables' "
                      "sources, and carries its marks (split 'probe', probe columns); no result file the tables read "
                      "holds a probe column, a row of split 'probe', or a served ratio equal to a probe number (a "
                      "snapshot's value on the probe day other than the one its job's evaluation recorded).")
    files = probe_files(ctx)
    probes: list[dict] = []
    for path in files:
        df = _read(ctx, chk, path)
        if df is not None:
            probes.extend(_probe_rows(ctx, chk, path, df))
    by_day: dict[tuple[str, int], list[dict]] = {}
    for p in probes:
        if not p["own"]:  # the evaluation's own number is no probe number
            by_day.setdefault((str(p["dataset"]), int(p["day"])), []).append(p)
    sources = []
    for ds in ctx.datasets:
        for method, seed, path, df in _results(ctx, chk, ds):
            where = ctx.rel(path)
            sources.append(where)
            stray = [f for f in (PROBE_FILE, PROBE_RECORD_FILE) if (path.parent / f).exists()]
            if stray:
                chk.fail(f"{where}: its directory holds the probe file(s) {stray} — probe numbers belong under "
                         f"results/probes/, apart from the tables' sources")
            cols = [c for c in PROBE_COLUMNS if c in df.columns]
            if cols:
                chk.fail(f"{where}: holds the probe column(s) {cols} — probe rows were copied into a table's source; "
                         f"re-run its evaluate job")
            if "split" in df.columns:
                n = df.filter(pl.col("split") == PROBE_SPLIT).height
                if n:
                    chk.fail(f"{where}: {n} row(s) of split {PROBE_SPLIT!r} — probe rows in a table's source; re-run "
                             f"its evaluate job")
            if not {"day", "sr_mean"} <= set(df.columns):
                continue
            for r in df.iter_rows(named=True):
                for p in by_day.get((ds, int(r["day"])), []):
                    if r["sr_mean"] != p["sr_mean"]:
                        continue
                    what = ("the trained model" if p["final"] else
                            f"the checkpoint at fraction {p['fraction']} of the budget")
                    chk.fail(f"{where}: day {r.get('label', r['day'])} has sr_mean = {r['sr_mean']!r}, the probe "
                             f"value of {what} of {p['method']}/seed{p['seed']} ({p['n_transitions']} transitions) "
                             f"in {p['where']} — a probe number copied into a table's source; re-run its evaluate "
                             f"job")
    chk.evidence = {"probe_files": [ctx.rel(p) for p in files], "probe_rows": len(probes),
                    "table_sources": len(sources),
                    "rows_equal_to_their_evaluation": sorted(f"{p['where']} fraction {p['fraction']}"
                                                             for p in probes if p["own"])}
    if not ctx.read_probes:
        chk.evidence["note"] = PROBES_LEFT_OUT
    elif not files:
        chk.evidence["note"] = ("no probe file in this run (the sample-efficiency probe has not run): nothing to "
                                "compare")
    return chk
