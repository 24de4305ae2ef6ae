"""Paper Fig. 8 (ablation): (a) DSWM against its ablations, served ratio on weekdays and holidays from the main
result files; (b) the do(s) probe, served ratio when the demand the planner imagines is scaled by s at decision
time (``planner.imagine_scale``), the extra runs of workflow/rules/extra.smk, against s = 1 (the main evaluation
on the same days)."""
from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import polars as pl

from dswm.figures.common import mean_std, plt, save_figure
from dswm.figures.variants import line_label, reference_rows, with_variant
from dswm.settings import EvalDayLimits

ABLATION_METHODS = ("dswm", "dswm_wo_unc", "dswm_wo_dec", "dswm_plus", "dswm_plus_persist")
"""DSWM, its two ablations and DSWM+ with its persistence probe: panel (a), those evaluated."""
SPLITS = ("id", "ood")
CAPTION = ("Paper Fig. 8 (ablation): (a) DSWM against its ablations, served ratio (mean ± std over seeds); "
           "(b) do(s): imagined demand x s at planning time; dashed/dotted: s = 1, the main evaluation on the "
           "same days.")


def do_probe_days(main: pl.DataFrame, runs: pl.DataFrame | None, *, methods: Sequence[str], seeds: Sequence[int],
                  limits: EvalDayLimits) -> pl.DataFrame:
    """The rows of panel (b): the do(s) runs (``runs``, their ``variant`` column do<s>) and s = 1, ``main``'s rows of
    ``methods`` and ``seeds`` on the same days (:func:`dswm.figures.variants.reference_rows`); column ``scale``."""
    runs = with_variant(runs)
    ref = reference_rows(main, runs, methods=methods, seeds=seeds, limits=limits, kind="do", value=1.0,
                         what="do(s) probe")
    cols = ["method", "seed", "split", "day", "sr_mean", "value"]
    return pl.concat([ref.select(cols), runs.select(cols)]).rename({"value": "scale"})


def ablation_table(ablation: pl.DataFrame, probe: pl.DataFrame) -> pl.DataFrame:
    """The numbers drawn: per (panel, method, split[, scale]) the served ratio's mean over seeds of each seed's mean
    day, its std over seeds and the number of seeds (:func:`dswm.figures.common.mean_std`)."""
    a = mean_std(ablation, ["method", "split"], "sr_mean").with_columns(panel=pl.lit("a"),
                                                                        scale=pl.lit(None, pl.Float64))
    b = mean_std(probe, ["method", "split", "scale"], "sr_mean").with_columns(panel=pl.lit("b"))
    cols = ["panel", "method", "split", "scale", "sr_mean", "sr_mean_std", "seeds"]
    return pl.concat([a.select(cols), b.select(cols)]).sort(["panel", "method", "split", "scale"], nulls_last=True,
                                                           maintain_order=True)


def draw_ablation(ablation: pl.DataFrame, probe: pl.DataFrame, *, order: Sequence[str], labels: Mapping[str, str],
                  split_labels: Mapping[str, str], profile: str, source: str,
                  out: Mapping[str, str | Path]) -> pl.DataFrame:
    """Draw paper Fig. 8 and write it (PNG, PDF, CSV of :func:`ablation_table`).

    Args:
        ablation: per-day rows (method, seed, split, sr_mean) of the main evaluations of the ablation methods.
        probe: per-day rows of panel (b) with a ``scale`` column (:func:`do_probe_days`).
        order: the methods of panel (a), left to right (``methods.run`` order).
        labels: {method: label}; split_labels: {"id": ..., "ood": ...} (the tables' column names).
        out: {"png", "pdf", "csv"} paths.
    Returns:
        The table written as CSV.
    """
    table = ablation_table(ablation, probe)
    fig, (ax_a, ax_b) = plt.subplots(1, 2, figsize=(11.0, 4.4), gridspec_kw={"width_ratios": [1.3, 1.0]})
    part = table.filter(pl.col("panel") == "a")
    order = [m for m in order if m in set(part["method"])]
    x, width = np.arange(len(order)), 0.4
    for i, split in enumerate(SPLITS):
        rows = {r["method"]: r for r in part.filter(pl.col("split") == split).iter_rows(named=True)}
        if not rows:
            continue
        mean = [rows[m]["sr_mean"] if m in rows else np.nan for m in order]
        std = [rows[m]["sr_mean_std"] if m in rows else 0.0 for m in order]
        bars = ax_a.bar(x + (i - 0.5) * width, mean, width, yerr=std, capsize=2, label=split_labels[split],
                        color=("tab:blue", "tab:orange")[i])
        ax_a.bar_label(bars, fmt="%.3f", fontsize=6, padding=2)
    ax_a.set_xticks(x, [labels.get(m, m) for m in order], rotation=20, ha="right", fontsize=8)
    ax_a.set_ylabel("served ratio")
    ax_a.set_title("(a) DSWM and its ablations", fontsize=10)
    ax_a.legend(fontsize=8, loc="lower right")
    ax_a.grid(axis="y", alpha=0.3)
    low = part["sr_mean"].min()
    if low is not None:
        ax_a.set_ylim(max(0.0, float(low) - 0.15), 1.0)

    part = table.filter(pl.col("panel") == "b")
    probed = list(dict.fromkeys(part["method"].to_list()))
    splits = [sp for sp in SPLITS if sp in set(part["split"])]
    colors = dict(zip(probed, plt.rcParams["axes.prop_cycle"].by_key()["color"]))
    for (method, split), rows in part.group_by(["method", "split"], maintain_order=True):
        rows = rows.sort("scale")
        style = "o-" if split == "id" else "s-."
        ax_b.errorbar(rows["scale"].to_numpy(), rows["sr_mean"].to_numpy(), yerr=rows["sr_mean_std"].to_numpy(),
                      fmt=style, capsize=3, color=colors[method],
                      label=line_label(labels.get(method, method), split, splits, split_labels))
        ref = rows.filter(pl.col("scale") == 1.0)
        if ref.height:
            ax_b.axhline(ref["sr_mean"][0], color=colors[method], ls="--" if method == probed[0] else ":", lw=0.8)
    ax_b.set_xscale("log", base=2)
    scales = sorted(set(part["scale"].to_list()))
    ax_b.set_xticks(scales, [f"{s:g}" for s in scales])
    ax_b.set_xlabel("s (imagined demand x s at planning time)")
    ax_b.set_ylabel("served ratio" + (f" ({split_labels[splits[0]]})" if len(splits) == 1 else ""))
    ax_b.set_title("(b) counterfactual do(s)", fontsize=10)
    ax_b.legend(fontsize=8)
    ax_b.grid(alpha=0.3)
    fig.tight_layout(rect=(0, 0.05, 1, 1))
    save_figure(fig, table, png=out["png"], pdf=out["pdf"], csv=out["csv"], profile=profile, source=source,
                caption=CAPTION)
    return table
