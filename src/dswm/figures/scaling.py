"""Paper Fig. 10 (scaling): served ratio against the fleet size K and against a factor of the demand intensity u,
one line per method, from the extra runs of workflow/rules/extra.smk (scenario overrides of the same code) and,
at the scenario's own K and u x 1, the main evaluation on the same days."""
from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence

import polars as pl

from dswm.figures.common import mean_std, plt, save_figure
from dswm.figures.variants import line_label, reference_rows, with_variant
from dswm.settings import EvalDayLimits

SWEEPS = (("K", "fleet size K (UAVs)"), ("u", "demand intensity (x u)"))
"""The two panels: the variant kind each sweeps and its axis label."""
CAPTION = ("Paper Fig. 10 (scaling): served ratio against fleet size K and demand intensity (u x factor), "
           "mean ± std over seeds; dotted: the scenario's own K and u (the main evaluation on the same days).")


def scaling_days(main: pl.DataFrame, runs: pl.DataFrame | None, *, methods: Sequence[str], seeds: Sequence[int],
                 limits: EvalDayLimits, n_uavs: int, fleet_sizes: Sequence[int],
                 intensity_scales: Sequence[float]) -> pl.DataFrame:
    """The rows drawn: the K and u runs (``runs``, their ``variant`` column K<k> / u<f>) and, where the sweep holds
    the scenario's own point (K = ``n_uavs``, factor 1), ``main``'s rows of ``methods`` and ``seeds`` on the same
    days; columns method, seed, split, day, sr_mean, sweep ("K" or "u"), value (K or the factor)."""
    runs = with_variant(runs)
    cols = ["method", "seed", "split", "day", "sr_mean", "kind", "value"]
    parts = [runs.select(cols)]
    for kind, own, sweep in (("K", float(n_uavs), fleet_sizes), ("u", 1.0, intensity_scales)):
        if own in {float(v) for v in sweep}:
            ref = reference_rows(main, runs.filter(pl.col("kind") == kind), methods=methods, seeds=seeds,
                                 limits=limits, kind=kind, value=own, what=f"scaling sweep {kind}")
            parts.append(ref.select(cols))
    return pl.concat(parts).rename({"kind": "sweep"})


def draw_scaling(days: pl.DataFrame, *, order: Sequence[str], labels: Mapping[str, str],
                 split_labels: Mapping[str, str], reference: Mapping[str, float], profile: str, source: str,
                 out: Mapping[str, str | Path]) -> pl.DataFrame:
    """Draw paper Fig. 10 and write it (PNG, PDF and the CSV of the numbers drawn).

    Args:
        days: per-day rows of :func:`scaling_days` (method, seed, split, sr_mean, sweep, value).
        order: the methods, in legend order; labels: {method: label}; split_labels: {"id": ..., "ood": ...}.
        reference: {"K": the scenario's K, "u": 1.0}, marked by a dotted line.
        out: {"png", "pdf", "csv"} paths.
    Returns:
        The CSV's table: per (sweep, method, split, value) the served ratio's mean over seeds of each seed's mean
        day, its std over seeds and the number of seeds.
    """
    table = mean_std(days, ["sweep", "method", "split", "value"], "sr_mean").sort(
        ["sweep", "method", "split", "value"], maintain_order=True)
    order = [m for m in order if m in set(table["method"])]
    colors = dict(zip(order, plt.rcParams["axes.prop_cycle"].by_key()["color"]))
    fig, axes = plt.subplots(1, 2, figsize=(10.0, 4.2))
    for ax, (sweep, xlabel), tag in zip(axes, SWEEPS, "ab"):
        part = table.filter(pl.col("sweep") == sweep)
        splits = [sp for sp in ("id", "ood") if sp in set(part["split"])]
        for method in order:
            for split in ("id", "ood"):
                rows = part.filter((pl.col("method") == method) & (pl.col("split") == split)).sort("value")
                if not rows.height:
                    continue
                several = bool((rows["seeds"] > 1).any())
                ax.errorbar(rows["value"].to_numpy(), rows["sr_mean"].to_numpy(),
                            yerr=rows["sr_mean_std"].to_numpy() if several else None,
                            fmt="o-" if split == "id" else "s-.", capsize=3, color=colors[method],
                            label=line_label(labels.get(method, method), split, splits, split_labels))
        values = sorted(set(part["value"].to_list()))
        if sweep == "u":
            ax.set_xscale("log", base=2)
        if values:
            ax.set_xticks(values, [f"{v:g}" for v in values])
        if sweep in reference:
            ax.axvline(reference[sweep], color="0.5", ls=":", lw=0.8)
        ax.set_xlabel(xlabel)
        ax.set_ylabel("served ratio" + (f" ({split_labels[splits[0]]})" if len(splits) == 1 else ""))
        ax.set_title(f"({tag}) " + ("fleet size" if sweep == "K" else "demand intensity"), fontsize=10)
        ax.grid(alpha=0.3)
        if part.height:
            ax.legend(fontsize=8)
    fig.tight_layout(rect=(0, 0.05, 1, 1))
    save_figure(fig, table, png=out["png"], pdf=out["pdf"], csv=out["csv"], profile=profile, source=source,
                caption=CAPTION)
    return table
