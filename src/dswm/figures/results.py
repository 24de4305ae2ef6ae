"""Figures of the evaluation results (the files the tables are built from): main results (paper Fig. 7), OOD
analysis (paper Fig. 6) and the cross-dataset comparison (paper Fig. 13).

Each ``draw_*`` takes the per-day rows of the result files (``common.read_days``), the methods' labels, classes
and ``methods.run`` order and the table settings, and writes PNG + PDF + CSV through :func:`dswm.figures.common.save_figure`.
"""
from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import polars as pl

from dswm.figures.common import mean_std, plt, save_figure
from dswm.protocol.tables import DATASET_LABELS

SPLITS = (("id", "weekday"), ("ood", "holiday"))
MAIN_METRICS = (("sr_mean", "served ratio"), ("energy_kj_per_slot", "energy per slot (kJ)"),
                ("energy_efficiency", "energy efficiency"))
"""The three panels of paper Fig. 7: (a) served ratio, (b) energy per slot, (c) energy efficiency."""


def method_order(methods: Sequence[str], classes: Mapping[str, str], class_order: Sequence[str]) -> list[str]:
    """``methods`` grouped by class in ``class_order`` (unknown classes last), the given order within a class: the
    row order of Table III."""
    rank = {c: i for i, c in enumerate(class_order)}
    methods = list(methods)
    return sorted(methods, key=lambda m: (rank.get(classes[m], len(rank)), methods.index(m)))


def in_order(df: pl.DataFrame, order: Sequence[str], *then: str) -> pl.DataFrame:
    """``df``'s rows with methods in ``order`` (every method of ``df`` must be in it), then sorted by ``then``."""
    return df.sort(pl.col("method").replace_strict({m: i for i, m in enumerate(order)}), *then)


def split_summary(days: pl.DataFrame, value: str) -> pl.DataFrame:
    """Per (dataset, method, split): ``value``'s mean over seeds of each seed's mean day, its sample std and the
    number of seeds (:func:`dswm.figures.common.mean_std`)."""
    return mean_std(days, ["dataset", "method", "split"], value)


def _bars(ax, order, labels, table: pl.DataFrame, value: str, ylabel: str, split_labels: Mapping[str, str]):
    """Weekday and holiday bars with seed-std error bars, one pair per method of ``order``."""
    x = np.arange(len(order))
    width = 0.4
    for i, (split, _) in enumerate(SPLITS):
        rows = {r["method"]: r for r in table.filter(pl.col("split") == split).iter_rows(named=True)}
        # no bar where a method lacks the metric (the per-slot ceiling flies no fleet: no energy)
        mean = [rows[m][value] if m in rows and rows[m][value] is not None else np.nan for m in order]
        std = [rows[m][value + "_std"] if m in rows and rows[m][value + "_std"] is not None else 0.0 for m in order]
        ax.bar(x + (i - 0.5) * width, mean, width, yerr=std, capsize=2, label=split_labels[split],
               color=("tab:blue", "tab:orange")[i])
    ax.set_xticks(x, [labels[m] for m in order], rotation=60, ha="right", fontsize=7)
    ax.set_ylabel(ylabel)
    ax.grid(axis="y", alpha=0.3)


def _class_spans(ax, order, classes):
    """Shade alternate method classes and name each above the axis."""
    start = 0
    for i in range(1, len(order) + 1):
        if i == len(order) or classes[order[i]] != classes[order[start]]:
            if (len({classes[m] for m in order[:start]}) % 2) == 1:
                ax.axvspan(start - 0.5, i - 0.5, color="0.93", zorder=0)
            ax.text((start + i - 1) / 2, 1.01, classes[order[start]], transform=ax.get_xaxis_transform(),
                    ha="center", va="bottom", fontsize=6, rotation=30)
            start = i


def draw_main(days: pl.DataFrame, *, dataset: str, labels: Mapping[str, str], classes: Mapping[str, str],
              run_order: Sequence[str], class_order: Sequence[str], split_labels: Mapping[str, str], profile: str, source: str,
              out: Mapping[str, str | Path]) -> pl.DataFrame:
    """Paper Fig. 7: served ratio, energy per slot and energy efficiency per method on ``dataset``, weekday and
    holiday bars, grouped by class. Returns (and writes as CSV) one row per (method, split) with each metric's
    mean and std over seeds."""
    days = days.filter(pl.col("dataset") == dataset)
    order = method_order([m for m in run_order if m in set(days["method"])], classes, class_order)
    table = None
    for value, _ in MAIN_METRICS:
        s = split_summary(days, value).drop("dataset")
        table = s if table is None else table.join(s.drop("seeds"), on=["method", "split"], how="left")
    fig, axes = plt.subplots(3, 1, figsize=(max(8.0, 0.5 * len(order) + 2), 11.5), sharex=True)
    for ax, (value, ylabel), tag in zip(axes, MAIN_METRICS, "abc"):
        _bars(ax, order, labels, table, value, f"({tag}) {ylabel}", split_labels)
        _class_spans(ax, order, classes)
    axes[0].set_ylim(0, 1.12)
    lo = table["energy_kj_per_slot"].min()
    hi = table["energy_kj_per_slot"].max()
    axes[1].set_ylim(lo - max(5.0, 0.5 * (hi - lo)), hi + max(5.0, 0.5 * (hi - lo)))  # a ~3% spread is visible
    axes[0].legend(fontsize=8, ncol=2, loc="upper right")
    fig.tight_layout(rect=(0, 0.03, 1, 1))
    data = table.with_columns(pl.col("method").replace_strict(labels, default=None).alias("label"),
                              pl.col("method").replace_strict(classes, default=None).alias("class"))
    data = in_order(data, order, "split")
    save_figure(fig, data, **out, profile=profile, source=source,
                caption=f"Paper Fig. 7 (main): {DATASET_LABELS.get(dataset, dataset)} main results per method, "
                        f"grouped by class: (a) served ratio, (b) energy per slot, (c) energy efficiency "
                        f"({split_labels['id']} ID / {split_labels['ood']} OOD; mean±std over seeds).")
    return data


def draw_ood(days: pl.DataFrame, *, dataset: str, labels: Mapping[str, str], classes: Mapping[str, str],
             run_order: Sequence[str], class_order: Sequence[str], split_labels: Mapping[str, str], profile: str, source: str,
             out: Mapping[str, str | Path]) -> pl.DataFrame:
    """Paper Fig. 6: (a) each method's degradation, weekday minus holiday served ratio (mean over seeds of each
    seed's difference); (b) the served ratio of every evaluated day of the test period (mean over seeds), one
    marker set per method, holidays shaded. Returns (and writes as CSV) the per-day rows of (b) with the
    degradation of (a) beside each method."""
    days = days.filter(pl.col("dataset") == dataset)
    order = method_order([m for m in run_order if m in set(days["method"])], classes, class_order)
    per_seed = days.group_by("method", "seed", "split").agg(pl.col("sr_mean").mean())
    wide = per_seed.pivot(on="split", index=["method", "seed"], values="sr_mean")
    deg = (wide.with_columns((pl.col("id") - pl.col("ood")).alias("degradation"))
           .group_by("method").agg(pl.col("degradation").mean(),
                                   pl.col("degradation").std(ddof=1).fill_null(0.0).alias("degradation_std")))
    deg_of = {r["method"]: r for r in deg.iter_rows(named=True)}
    per_day = (days.group_by("method", "day", "label", "split")
               .agg(pl.col("sr_mean").mean(), pl.col("sr_mean").std(ddof=1).fill_null(0.0).alias("sr_std"),
                    pl.col("seed").n_unique().alias("seeds"))
               .sort("day"))
    fig, (ax_a, ax_b) = plt.subplots(1, 2, figsize=(12, 5.5), gridspec_kw={"width_ratios": [1, 1.3]})
    y = np.arange(len(order))
    vals = [deg_of[m]["degradation"] for m in order]
    ax_a.barh(y, vals, xerr=[deg_of[m]["degradation_std"] for m in order], capsize=2,
              color=["tab:red" if v > 0 else "tab:green" for v in vals])
    ax_a.set_yticks(y, [labels[m] for m in order], fontsize=7)
    ax_a.invert_yaxis()
    ax_a.axvline(0, color="k", lw=0.8)
    ax_a.set_xlabel(f"(a) degradation: {split_labels['id']} minus {split_labels['ood']} served ratio")
    ax_a.grid(axis="x", alpha=0.3)
    day_list = per_day.select("day", "label", "split").unique().sort("day")
    xpos = {d: i for i, d in enumerate(day_list["day"])}
    for i, r in enumerate(day_list.iter_rows(named=True)):
        if r["split"] == "ood":
            ax_b.axvspan(i - 0.5, i + 0.5, color="0.9", zorder=0)
    cmap = plt.get_cmap("tab20")
    markers = "os^vD<>pPX*h"
    for k, m in enumerate(order):
        rows = per_day.filter(pl.col("method") == m)
        ax_b.plot([xpos[d] for d in rows["day"]], rows["sr_mean"], marker=markers[k % len(markers)], ms=4, lw=0.8,
                  color=cmap(k % 20), label=labels[m])
    ax_b.set_xticks(range(len(day_list)), [f"{lab}\n({split_labels[s]})" for lab, s in
                                            zip(day_list["label"], day_list["split"])], fontsize=7)
    ax_b.set_ylabel("(b) served ratio per evaluated day")
    ax_b.grid(alpha=0.3)
    ax_b.legend(fontsize=6, ncol=2, loc="center left", bbox_to_anchor=(1.01, 0.5))
    fig.tight_layout(rect=(0, 0.03, 1, 1))
    data = per_day.join(deg, on="method", how="left").with_columns(
        pl.col("method").replace_strict(labels, default=None).alias("label_method"))
    data = in_order(data, order, "day")
    save_figure(fig, data, **out, profile=profile, source=source,
                caption=f"Paper Fig. 6 (ood): OOD analysis on {DATASET_LABELS.get(dataset, dataset)} over the test "
                        f"period: (a) per-method degradation ({split_labels['id']} minus {split_labels['ood']}); "
                        f"(b) served ratio per evaluated day, {split_labels['ood']} days shaded.")
    return data


def draw_cross(days: pl.DataFrame, *, labels: Mapping[str, str], classes: Mapping[str, str],
               run_order: Sequence[str], class_order: Sequence[str], split_labels: Mapping[str, str], profile: str,
               source: Mapping[str, str], out: Mapping[str, str | Path]) -> pl.DataFrame:
    """Paper Fig. 13: grouped bars of Table IV, one panel per split, one bar per dataset for each method that
    runs on more than one dataset. Returns (and writes as CSV) the (method, dataset, split) means and stds."""
    datasets = [d for d in DATASET_LABELS if d in set(days["dataset"])]
    table = split_summary(days, "sr_mean")
    runs_on = table.group_by("method").agg(pl.col("dataset").n_unique().alias("n"))
    shared = set(runs_on.filter(pl.col("n") > 1)["method"]) if len(datasets) > 1 else set(runs_on["method"])
    order = method_order([m for m in run_order if m in shared], classes, class_order)
    fig, axes = plt.subplots(1, 2, figsize=(max(9.0, 0.6 * len(order) + 3), 4.8), sharey=True)
    width = 0.8 / max(1, len(datasets))
    x = np.arange(len(order))
    for ax, (split, _) in zip(axes, SPLITS):
        for i, ds in enumerate(datasets):
            rows = {r["method"]: r for r in table.filter((pl.col("split") == split) & (pl.col("dataset") == ds))
                    .iter_rows(named=True)}
            ax.bar(x + (i - (len(datasets) - 1) / 2) * width, [rows[m]["sr_mean"] if m in rows else np.nan
                                                                for m in order], width,
                   yerr=[rows[m]["sr_mean_std"] if m in rows else 0.0 for m in order], capsize=2,
                   label=DATASET_LABELS[ds])
        ax.set_xticks(x, [labels[m] for m in order], rotation=60, ha="right", fontsize=7)
        ax.set_title(f"{split_labels[split]} served ratio", fontsize=10, pad=14)
        ax.set_ylim(0, 1.12)
        ax.grid(axis="y", alpha=0.3)
    axes[0].legend(fontsize=8, ncol=len(datasets), loc="upper center")
    fig.tight_layout(rect=(0, 0.04, 1, 1))
    data = in_order(table.filter(pl.col("method").is_in(order)).with_columns(
        pl.col("method").replace_strict(labels, default=None).alias("label")), order, "dataset", "split")
    seeds = ", ".join(f"{DATASET_LABELS[d]} {table.filter(pl.col('dataset') == d)['seeds'].max()}" for d in datasets)
    save_figure(fig, data, **out, profile=profile, source=source,
                caption=f"Paper Fig. 13 (cross_dataset): Table IV as grouped bars, {split_labels['id']} and "
                        f"{split_labels['ood']} served ratio per dataset (mean±std over seeds: {seeds}).")
    return data


def figure_job(name: str, *, job: Mapping, mlflow_cfg: Mapping, inputs, out: Mapping[str, str | Path]) -> pl.DataFrame:
    """Draw figure ``name`` (main, ood, cross_dataset or eda) for its rule and log it (PNG and PDF) as an artifact
    of every evaluation run it shows.

    Args:
        job: the plain form of ``dswm.settings.figures_slice`` (profile, tables, datasets, methods in run order,
            the MLflow experiment).
        mlflow_cfg: the ``mlflow`` section (``dswm.settings.tracking``): where the runs it is attached to are.
        inputs: the rule's input: ``results`` (every days.parquet of the profile) and, per dataset, its meta.json
            (``<dataset>``) or, for eda, its EDA statistics (``eda_<dataset>``).
    """
    from dswm.figures.eda import draw_eda, read_stats

    profile = job["profile"]
    if name == "eda":
        return draw_eda(read_stats({d: inputs[f"eda_{d}"] for d in job["datasets"]}), profile=profile, out=out)
    data = _draw(name, job=job, inputs=inputs, out=out)
    # The figure is logged beside the evaluation runs it shows (every dataset's for cross_dataset).
    from dswm.pipeline.tracking import attach_figures

    attach_figures(mlflow_cfg=mlflow_cfg, paths=[out["png"], out["pdf"]], stage="evaluate", profile=profile,
                   datasets=None if name == "cross_dataset" else [job["tables"]["main_dataset"]])
    return data


def _draw(name: str, *, job: Mapping, inputs, out: Mapping[str, str | Path]) -> pl.DataFrame:
    """The drawing part of :func:`figure_job` for main, ood and cross_dataset."""
    from dswm.figures.common import read_days
    from prep.tensor import read_meta

    profile = job["profile"]
    tables = job["tables"]
    methods = job["methods"]
    kw = dict(labels={m["name"]: m["label"] for m in methods}, classes={m["name"]: m["table_class"] for m in methods},
              run_order=[m["name"] for m in methods], class_order=tables["class_order"],
              split_labels=tables["split_labels"], profile=profile, out=out)
    days = read_days(list(inputs["results"]))
    sources = {d: read_meta(inputs[d], keys=("source",))["source"] for d in job["datasets"]}
    if name == "cross_dataset":
        return draw_cross(days, source={DATASET_LABELS[d]: s for d, s in sources.items()}, **kw)
    main = tables["main_dataset"]
    draw = {"main": draw_main, "ood": draw_ood}[name]
    return draw(days, dataset=main, source=sources[main], **kw)
