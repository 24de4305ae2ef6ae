"""The paper's two result tables, assembled from the per-day result files only (never logs or MLflow).

* ``<main>_main`` (Table III; ``milan_main`` by default): per method, the weekday (ID) and holiday (OOD) served
  ratio on ``tables.main_dataset``, mean and standard deviation over seeds, rows grouped by method class; then
  energy per slot (kJ), energy efficiency and Jain's index per split, the same way (paper Table III (b), (c) and
  the fairness text).
* ``cross_dataset`` (Table IV): the same per (method, dataset).

A seed's score on a split is the mean of its days' ``sr_mean``; the table reports mean and sample standard
deviation (ddof=1; 0 with a single seed) of those scores over seeds. The numbers come from one SQL query
(``dswm.protocol.results_db.SUMMARY_SQL``), the one behind the ``summary`` view of ``results/results.duckdb``, which
``build_tables`` writes beside the tables when asked. Each table states the profile and
whether each dataset's data was the embedded demo or the real published files. Every file is written in
Markdown, LaTeX and CSV (the CSV columns are fixed for other tools).

Both tables carry a footnote on the room a forecast could fill (``tables.room``): per dataset and split, the
served ratio from a method that plans on the current map (Greedy) to one that plans on the true future maps
(the perfect forecast), and the share of that room each forecasting method fills; then the ladder of references
and bounds (``tables.room.ladder``: Static -> Greedy -> Oracle -> Perfect -> Ceiling), from holding the deployment
to the per-slot ceiling no controller can pass. ``room.csv`` holds the numbers of both.
"""
from __future__ import annotations

import csv
import io
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import polars as pl

from dswm.protocol import results_db
from prep.atomic import write_text
from prep.tensor import read_meta

ROOM_COLUMNS = ["dataset", "split", "low", "high", "low_mean", "high_mean", "room", "method", "method_mean",
                "filled", "rung"]
EXTRA_METRICS = {"energy": "energy_kj_per_slot", "efficiency": "energy_efficiency", "jain": "jain"}
"""Table III's metrics besides the served ratio: {column prefix: days.parquet column}."""
EXTRA_LABELS = {"energy": "Energy (kJ/slot)", "efficiency": "Efficiency", "jain": "Jain"}
MAIN_COLUMNS = ["method", "class", "weekday_mean", "weekday_std", "holiday_mean", "holiday_std", "n_seeds",
                *(f"{p}_{w}_{s}" for p in EXTRA_METRICS for w in ("weekday", "holiday") for s in ("mean", "std"))]
CROSS_COLUMNS = ["method", "dataset", "weekday_mean", "weekday_std", "holiday_mean", "holiday_std", "n_seeds"]
DATASET_LABELS = {"milan": "Milan", "shanghai": "Shanghai", "yjmob": "YJMob"}
REQUIRED = {"dataset", "method", "seed", "split", "day", "sr_mean", "profile"}


def read_results(paths: Iterable[str | Path]) -> pl.DataFrame:
    """Concatenate per-day result files; refuse a file that lacks a required column or has no rows. The columns of
    :data:`EXTRA_METRICS` are kept (null where a file lacks one)."""
    frames = []
    for p in paths:
        df = pl.read_parquet(p)
        missing = REQUIRED - set(df.columns)
        if missing:
            raise ValueError(f"{p}: result file lacks column(s) {sorted(missing)}; expected {sorted(REQUIRED)}")
        if df.height == 0:
            raise ValueError(f"{p}: result file has no rows; expected one row per evaluated day")
        extra = [pl.col(c).cast(pl.Float64) if c in df.columns else pl.lit(None, pl.Float64).alias(c)
                 for c in EXTRA_METRICS.values()]
        frames.append(df.select(*sorted(REQUIRED), *extra))
    if not frames:
        raise ValueError("no result files given; expected results/{dataset}/{method}/seed{seed}/days.parquet")
    return pl.concat(frames)


def _order(methods: list[str], classes: Mapping[str, str], class_order: list[str]) -> list[str]:
    """Methods grouped by class in ``class_order`` (unknown classes last), run order within a class."""
    rank = {c: i for i, c in enumerate(class_order)}
    return sorted(methods, key=lambda m: (rank.get(classes[m], len(rank)), methods.index(m)))


def _csv(rows: list[dict], columns: list[str]) -> str:
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=columns, lineterminator="\n")
    writer.writeheader()
    writer.writerows({c: r[c] for c in columns} for r in rows)
    return buf.getvalue()


def _fmt(mean: float, std: float, n: int, d: int) -> str:
    return f"{mean:.{d}f}±{std:.{d}f}" if n > 1 else f"{mean:.{d}f}"


def _fmt_opt(mean: float | None, std: float | None, n: int, d: int) -> str:
    """:func:`_fmt`, or "--" where the result files lack the metric."""
    return "--" if mean is None else _fmt(mean, std, n, d)


def _tex_escape(text: str) -> str:
    for char, repl in (("&", r"\&"), ("%", r"\%"), ("_", r"\_"), ("#", r"\#"), ("±", r"$\pm$")):
        text = text.replace(char, repl)
    return text


def provenance(profile: str, sources: Mapping[str, str]) -> str:
    """The line every table carries: profile and the data source of each dataset."""
    data = ", ".join(f"{DATASET_LABELS.get(d, d)}: {s}" for d, s in sources.items())
    return f"profile: {profile}; data: {data}"


def build_tables(*, result_paths: Iterable[str | Path], meta_paths: Mapping[str, str | Path],
                 specs: Mapping[str, Any], run_order: list[str], tables_cfg: Mapping[str, Any],
                 profile: str, out_dir: str | Path, database: str | Path | None = None) -> dict[str, pl.DataFrame]:
    """Write <main_dataset>_main.{md,tex,csv}, cross_dataset.{md,tex,csv} and room.csv into ``out_dir``.

    Args:
        result_paths: every days.parquet of the profile.
        meta_paths: {dataset: meta.json of its prepared tensor} (for demo/real).
        specs: {method: MethodSpec} (label and class of each row).
        run_order: methods in config order.
        tables_cfg: the ``tables`` section (main_dataset, decimals, split_labels, class_order, room).
        profile: the profile the results must come from.
        out_dir: destination directory.
        database: where to write the DuckDB database of views ``days`` and ``summary`` over ``result_paths``
            (``results_db.write_database``; the paths are stored as given); None writes none.

    Returns:
        {"<main_dataset>_main": DataFrame, "cross_dataset": DataFrame} with the CSV columns.
    """
    result_paths = list(result_paths)
    days = read_results(result_paths)
    wrong = days.filter(pl.col("profile") != profile)
    if wrong.height:
        raise ValueError(f"result files hold profile {wrong['profile'][0]!r} rows, expected {profile!r} only "
                         f"(rerun the evaluate jobs of this profile)")
    summary = results_db.summary(results_db.connect(result_paths))
    if database is not None:
        results_db.write_database(database, result_paths)
    sources = {ds: read_meta(p, keys=("source",))["source"] for ds, p in meta_paths.items()}
    note = provenance(profile, sources)
    d = int(tables_cfg["decimals"])
    id_label, ood_label = tables_cfg["split_labels"]["id"], tables_cfg["split_labels"]["ood"]
    methods = [m for m in run_order if m in set(summary["method"])]
    classes = {m: specs[m].table_class for m in methods}
    order = _order(methods, classes, list(tables_cfg["class_order"]))
    out_dir = Path(out_dir)
    all_datasets = [ds for ds in DATASET_LABELS if ds in set(summary["dataset"])]
    room = room_rows(summary, tables_cfg["room"], all_datasets)
    write_text(out_dir / "room.csv", _csv(room, ROOM_COLUMNS))

    # Table III: the main dataset
    main_ds = tables_cfg["main_dataset"]
    if main_ds not in meta_paths:
        raise ValueError(f"config.yaml: key 'tables.main_dataset' is {main_ds!r}, which this run does not evaluate "
                         f"(datasets: {', '.join(meta_paths)})")
    main = summary.filter(pl.col("dataset") == main_ds)
    by_method = {r["method"]: r for r in main.iter_rows(named=True)}
    main_rows = [{"method": m, "class": classes[m], **{k: by_method[m][k] for k in MAIN_COLUMNS[2:]}}
                 for m in order if m in by_method]
    main_df = pl.DataFrame(main_rows, schema={c: pl.Float64 if "mean" in c or "std" in c else
                                              (pl.Int64 if c == "n_seeds" else pl.String) for c in MAIN_COLUMNS})
    title = (f"{DATASET_LABELS.get(main_ds, main_ds)} main results: served ratio "
             f"({id_label} ID / {ood_label} OOD), then energy per slot, energy efficiency and Jain's index "
             f"({id_label} / {ood_label}), mean±std over seeds")
    extra_heads = [f"{EXTRA_LABELS[p]} {lab}" for p in EXTRA_METRICS for lab in (id_label, ood_label)]
    md = [f"## {title}", "", f"_{note}_", "",
          f"| Method | Class | {id_label} | {ood_label} | " + " | ".join(extra_heads) + " | Seeds |",
          "|---|---|---|---|" + "---|" * len(extra_heads) + "---|"]
    tex_rows = []
    for r in main_rows:
        label = specs[r["method"]].label
        wk = _fmt(r["weekday_mean"], r["weekday_std"], r["n_seeds"], d)
        hd = _fmt(r["holiday_mean"], r["holiday_std"], r["n_seeds"], d)
        extra = [_fmt_opt(r[f"{p}_{w}_mean"], r[f"{p}_{w}_std"], r["n_seeds"], 1 if p == "energy" else d)
                 for p in EXTRA_METRICS for w in ("weekday", "holiday")]
        md.append(f"| {label} | {r['class']} | {wk} | {hd} | " + " | ".join(extra) + f" | {r['n_seeds']} |")
        tex_rows.append(f"{_tex_escape(label)} & {_tex_escape(r['class'])} & {_tex_escape(wk)} & "
                        f"{_tex_escape(hd)} & " + " & ".join(_tex_escape(e) for e in extra) + " \\\\")
    main_note = " ".join(note for note in (
        room_note([r for r in room if r["dataset"] == main_ds], specs, tables_cfg["split_labels"], d,
                  tables_cfg["room"]["min_room"], tables_cfg["room"]["fill"]),
        ladder_note([r for r in room if r["dataset"] == main_ds], specs, tables_cfg["split_labels"], d)) if note)
    if main_note:
        md += ["", main_note]
    tex = _tex_table(caption=f"{title}. {note}. {main_note}".rstrip(), label=f"tab:{main_ds}",
                     spec="@{}llcc" + "c" * len(extra_heads) + "@{}",
                     header=f"Method & Class & {id_label} & {ood_label} & "
                            + " & ".join(_tex_escape(h) for h in extra_heads) + " \\\\", rows=tex_rows)
    write_text(out_dir / f"{main_ds}_main.md", "\n".join(md) + "\n")
    write_text(out_dir / f"{main_ds}_main.tex", tex)
    write_text(out_dir / f"{main_ds}_main.csv", _csv(main_rows, MAIN_COLUMNS))

    # Table IV: every dataset
    datasets = [ds for ds in DATASET_LABELS if ds in set(summary["dataset"])]
    cells = {(r["method"], r["dataset"]): r for r in summary.iter_rows(named=True)}
    cross_rows = [{"method": m, "dataset": ds, **{k: cells[(m, ds)][k] for k in CROSS_COLUMNS[2:]}}
                  for m in order for ds in datasets if (m, ds) in cells]
    cross_df = pl.DataFrame(cross_rows, schema={c: pl.Float64 if "mean" in c or "std" in c else
                                                (pl.Int64 if c == "n_seeds" else pl.String) for c in CROSS_COLUMNS})
    title = f"Cross-dataset results: {id_label} / {ood_label} served ratio (mean over seeds)"
    heads = [f"{DATASET_LABELS[ds]}" for ds in datasets]
    md = [f"## {title}", "", f"_{note}_", "", "| Method | " + " | ".join(heads) + " |",
          "|---|" + "---|" * len(datasets)]
    tex_rows = []
    for m in order:
        vals = [f"{cells[(m, ds)]['weekday_mean']:.{d}f}/{cells[(m, ds)]['holiday_mean']:.{d}f}"
                if (m, ds) in cells else "--" for ds in datasets]
        md.append(f"| {specs[m].label} | " + " | ".join(vals) + " |")
        tex_rows.append(f"{_tex_escape(specs[m].label)} & " + " & ".join(vals) + " \\\\")
    seeds = "; ".join(f"{DATASET_LABELS[ds]} {summary.filter(pl.col('dataset') == ds)['n_seeds'].max()} seed(s)"
                      for ds in datasets)
    md += ["", f"Seeds: {seeds}."]
    cross_note = " ".join(note for note in (
        room_note(room, specs, tables_cfg["split_labels"], d, tables_cfg["room"]["min_room"],
                  tables_cfg["room"]["fill"]),
        ladder_note(room, specs, tables_cfg["split_labels"], d)) if note)
    if cross_note:
        md += ["", cross_note]
    tex = _tex_table(caption=f"{title}; {seeds}. {note}. {cross_note}".rstrip(), label="tab:cross", spec="@{}l" + "c" * len(datasets) + "@{}",
                     header="Method & " + " & ".join(heads) + " \\\\", rows=tex_rows)
    write_text(out_dir / "cross_dataset.md", "\n".join(md) + "\n")
    write_text(out_dir / "cross_dataset.tex", tex)
    write_text(out_dir / "cross_dataset.csv", _csv(cross_rows, CROSS_COLUMNS))
    return {f"{main_ds}_main": main_df, "cross_dataset": cross_df}


def room_rows(summary: pl.DataFrame, room: Mapping[str, Any], datasets: list[str]) -> list[dict]:
    """The room a forecast could fill and the ladder of bounds, per dataset and split (columns
    :data:`ROOM_COLUMNS`).

    Args:
        summary: the ``summary`` view (``dswm.protocol.results_db``).
        room: ``tables.room``: ``low`` (plans on the current map), ``high`` (plans on the true future maps),
            ``fill`` (the methods whose share of the room is reported), ``min_room`` (the smallest room whose
            share is reported: a share of a room within seed noise means nothing) and ``ladder`` (the references and
            bounds in order, e.g. static, greedy, oracle, perfect, ceiling).
        datasets: in table order.

    Returns:
        Per (dataset, split): one row per method of ``ladder`` present, ``rung`` its position in the ladder, then one
        per method of ``fill`` present (``rung`` None) that the ladder lacks. Room = high - low, filled = (method -
        low) / room (None when the room is below ``min_room``); no row for a dataset lacking ``low`` or ``high``.
    """
    cells = {(r["method"], r["dataset"]): r for r in summary.iter_rows(named=True)}
    ladder = list(room["ladder"])
    methods = [(m, i) for i, m in enumerate(ladder)] + [(m, None) for m in room["fill"] if m not in ladder]
    rows = []
    for ds in datasets:
        lo, hi = cells.get((room["low"], ds)), cells.get((room["high"], ds))
        if lo is None or hi is None:
            continue
        for split in ("weekday", "holiday"):
            gap = hi[f"{split}_mean"] - lo[f"{split}_mean"]
            for m, rung in methods:
                if (m, ds) not in cells:
                    continue
                got = cells[(m, ds)][f"{split}_mean"]
                rows.append({"dataset": ds, "split": split, "low": room["low"], "high": room["high"],
                             "low_mean": lo[f"{split}_mean"], "high_mean": hi[f"{split}_mean"], "room": gap,
                             "method": m, "method_mean": got,
                             "filled": (got - lo[f"{split}_mean"]) / gap if gap >= room["min_room"] else None,
                             "rung": rung})
    return rows


def room_note(rows: list[dict], specs: Mapping[str, Any], split_labels: Mapping[str, str], d: int,
              min_room: float, fill: Sequence[str]) -> str:
    """The footnote of :func:`room_rows`: per dataset and split, low -> high and the share each method of ``fill``
    fills."""
    rows = [r for r in rows if r["method"] in fill]
    if not rows:
        return ""
    first = rows[0]
    parts = []
    for ds in dict.fromkeys(r["dataset"] for r in rows):
        for split, key in (("weekday", "id"), ("holiday", "ood")):
            sel = [r for r in rows if r["dataset"] == ds and r["split"] == split]
            if not sel:
                continue
            fills = ", ".join(f"{specs[r['method']].label} {r['method_mean'] - r['low_mean']:+.{d}f}"
                              + ("" if r["filled"] is None else f" ({100 * r['filled']:.0f}%)") for r in sel)
            parts.append(f"{DATASET_LABELS.get(ds, ds)} {split_labels[key]} {sel[0]['low_mean']:.{d}f} -> "
                         f"{sel[0]['high_mean']:.{d}f} (room {sel[0]['room']:+.{d}f}; gained: {fills})")
    return (f"Room a forecast could fill, {specs[first['low']].label} -> {specs[first['high']].label}, and what "
            f"each method gains over {specs[first['low']].label} (its share of the room when the room is at least "
            f"{min_room:.{d}f}): " + "; ".join(parts) + ".")


def ladder_note(rows: list[dict], specs: Mapping[str, Any], split_labels: Mapping[str, str], d: int) -> str:
    """The ladder's footnote from the rows of :func:`room_rows` with a ``rung``: per dataset and split, each rung's
    served ratio in ladder order."""
    rows = sorted((r for r in rows if r.get("rung") is not None), key=lambda r: r["rung"])
    if not rows:
        return ""
    names = " -> ".join(specs[m].label for m in dict.fromkeys(r["method"] for r in rows))
    parts = []
    for ds in dict.fromkeys(r["dataset"] for r in rows):
        for split, key in (("weekday", "id"), ("holiday", "ood")):
            sel = [r for r in rows if r["dataset"] == ds and r["split"] == split]
            if sel:
                parts.append(f"{DATASET_LABELS.get(ds, ds)} {split_labels[key]} "
                             + " -> ".join(f"{r['method_mean']:.{d}f}" for r in sel))
    return f"Ladder of references and bounds, {names}: " + "; ".join(parts) + "."


def _tex_table(*, caption: str, label: str, spec: str, header: str, rows: list[str]) -> str:
    """A booktabs table environment."""
    return "\n".join([r"\begin{table}[!t]", r"\centering", f"\\caption{{{_tex_escape(caption)}}}",
                      f"\\label{{{label}}}", f"\\begin{{tabular}}{{{spec}}}", r"\toprule", header, r"\midrule",
                      *rows, r"\bottomrule", r"\end{tabular}", r"\end{table}", ""])
