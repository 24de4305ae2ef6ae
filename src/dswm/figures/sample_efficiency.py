"""Paper Fig. 9 (sample_efficiency): served ratio on the probe's fixed test day against the environment transitions
consumed (log scale), one line per probed method, from the probe files of workflow/rules/probes.smk
(``results/probes/<dataset>/<method>/seed<seed>/probe.parquet``, ``dswm.protocol.probe``).

The probe is diagnostic only: a fixed test-day probe of snapshots at fixed fractions of a fixed training budget, no
early stopping and no model selection; its numbers never enter a table (the audit's ``protocol.probes_out_of_tables``
proves it). Panel (b) draws the same numbers against the fraction of the budget done, where a method whose
transitions are all collected before its first gradient step (DSWM's pre-collection) shows its progress.
"""
from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence

import polars as pl

from dswm.figures.common import plt, save_figure

CAPTION = ("Paper Fig. 9 (sample_efficiency): served ratio on the probe day {day} ({dataset}, its first ID test day) "
           "of each method's snapshots at fractions {fractions} of its fixed training budget, against the "
           "environment transitions consumed (pre-collected ones included; log scale){spread}; (b) the same against "
           "the budget done (a method whose transitions are all collected before training, as DSWM's, stands at "
           "one x in (a)). Probe numbers: diagnostic only, no early stopping or model selection, never in a table.")



def probe_table(probes: pl.DataFrame) -> pl.DataFrame:
    """Per (method, fraction): the transitions consumed and the budget done at the snapshot (means over seeds), the
    served ratio's mean over seeds and its std over seeds (sample std; 0 for one seed), the number of seeds, and
    the probe day's label."""
    cols = ["method", "fraction", "fraction_done", "n_transitions", "sr_mean", "sr_mean_std", "seeds", "label",
            "dataset"]
    if probes.is_empty():
        return pl.DataFrame(schema={c: pl.Float64 for c in cols}).with_columns(
            pl.col("method", "label", "dataset").cast(pl.String), pl.col("seeds").cast(pl.UInt32))
    return (probes.group_by(["method", "fraction"], maintain_order=True)
            .agg(pl.col("fraction_done").mean(), pl.col("n_transitions").mean(), pl.col("sr_mean").mean(),
                 pl.col("sr_mean").std(ddof=1).fill_null(0.0).alias("sr_mean_std"), pl.col("seed").n_unique()
                 .alias("seeds"), pl.col("label").first(), pl.col("dataset").first())
            .sort(["method", "fraction"], maintain_order=True).select(cols))


def caption(table: pl.DataFrame, fractions: Sequence[float]) -> str:
    """The figure's caption, naming the probe day and the fractions."""
    days = sorted(set(table["label"].to_list())) if table.height else ["(none: no probed method)"]
    datasets = sorted(set(table["dataset"].to_list())) if table.height else ["-"]
    several = bool(table.height and (table["seeds"] > 1).any())
    return CAPTION.format(day=", ".join(days), dataset=", ".join(datasets),
                          fractions=", ".join(f"{f:g}" for f in fractions),
                          spread="; mean ± std over seeds" if several else "")


def draw_sample_efficiency(probes: pl.DataFrame, *, order: Sequence[str], labels: Mapping[str, str],
                           fractions: Sequence[float], profile: str, source: str,
                           out: Mapping[str, str | Path]) -> pl.DataFrame:
    """Draw paper Fig. 9 and write it (PNG, PDF and the CSV of the numbers drawn).

    Args:
        probes: the rows of the probe files (``dswm.figures.common.read_parquets``): method, seed, fraction, fraction_done,
            n_transitions, sr_mean, label, dataset.
        order: the methods, in legend order; labels: {method: label}; fractions: the requested budget fractions.
        out: {"png", "pdf", "csv"} paths.
    Returns:
        The CSV's table (:func:`probe_table`).
    """
    table = probe_table(probes)
    order = [m for m in order if m in set(table["method"].to_list())]
    colors = dict(zip(order, plt.rcParams["axes.prop_cycle"].by_key()["color"] * 3))
    fig, axes = plt.subplots(1, 2, figsize=(12.5, 4.6))
    for ax, (x, xlabel, title) in zip(axes, (
            ("n_transitions", "environment transitions (log scale)", "(a) against environment transitions"),
            ("fraction_done", "fraction of the training budget (log scale)", "(b) against the budget done"))):
        for method in order:
            rows = table.filter(pl.col("method") == method).sort(x)
            several = bool((rows["seeds"] > 1).any())
            ax.errorbar(rows[x].to_numpy(), rows["sr_mean"].to_numpy(),
                        yerr=rows["sr_mean_std"].to_numpy() if several else None, fmt="o-", capsize=3, ms=4,
                        color=colors[method], label=labels.get(method, method))
        ax.set_xscale("log", base=10 if x == "n_transitions" else 2)
        if x == "fraction_done":
            ax.set_xticks(list(fractions), [f"{f:g}" for f in fractions])
        ax.set_xlabel(xlabel)
        ax.set_ylabel("probe served ratio")
        ax.set_title(title, fontsize=10)
        ax.grid(alpha=0.3, which="both")
    if order:
        axes[1].legend(fontsize=8, loc="center left", bbox_to_anchor=(1.02, 0.5))
    else:
        for ax in axes:
            ax.text(0.5, 0.5, "no probed method in this profile", ha="center", va="center", transform=ax.transAxes)
    fig.tight_layout(rect=(0, 0.08, 1, 0.96))
    save_figure(fig, table, png=out["png"], pdf=out["pdf"], csv=out["csv"], profile=profile, source=source,
                caption=caption(table, fractions))
    return table
