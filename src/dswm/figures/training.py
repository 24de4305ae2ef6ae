"""Paper Fig. 11 (training): DSWM's training diagnostics per dataset, from the loss histories its train jobs write
(``results/<dataset>/dswm/seed<seed>/train_history.parquet``, ``dswm.pipeline.history``).

Each point of a history is the mean of a window of gradient steps (``dswm.training.log_points`` points per run);
a line is the mean over seeds of those points, the band its std over seeds."""
from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import polars as pl

from dswm.figures.common import plt, save_figure

PANELS = (
    ("(a) world-model loss", (("losses/loss", "L_WM"),), "linear"),
    ("(b) demand MSE (symlog)", (("losses/dem", "L_dem"),), "log"),
    ("(c) KL(q || p) (nats)", (("losses/kl", "KL"),), "linear"),
    ("(d) latent prediction", (("losses/lpr_pred", "L_LPR pred"), ("losses/lpr_var", "variance margin")), "linear"),
)
"""The four panels: title, the series drawn (history column, legend name) and the y scale."""
SERIES = tuple(name for _, series, _ in PANELS for name, _ in series)
CAPTION = ("Paper Fig. 11 (training): DSWM training diagnostics per dataset over gradient steps: world-model "
           "loss, demand MSE (symlog space), KL and the latent-prediction terms; mean over seeds (band: ± std).")


def summarize(histories: pl.DataFrame, series: Sequence[str] = SERIES) -> pl.DataFrame:
    """Per (dataset, series, step): the mean over seeds, its std over seeds (0 for one seed) and the seed count.

    Args:
        histories: rows of ``dswm.pipeline.history.read_histories`` (dataset, method, seed, step, one column per
            series).
    Raises:
        ValueError: a series is missing from the histories.
    """
    missing = [s for s in series if s not in histories.columns]
    if missing:
        raise ValueError(f"training histories lack the series {missing}; found {histories.columns} (expected the "
                         f"DSWM loss terms of dswm.methods.dswm.training.HISTORY_KEYS)")
    long = histories.unpivot(index=["dataset", "seed", "step"], on=list(series), variable_name="series",
                             value_name="value").drop_nulls("value")
    return (long.group_by(["dataset", "series", "step"], maintain_order=True)
            .agg(pl.col("value").mean(), pl.col("value").std(ddof=0).fill_null(0.0).alias("value_std"),
                 pl.len().alias("seeds"))
            .sort(["dataset", "series", "step"], maintain_order=True))


def draw_training(histories: pl.DataFrame, *, datasets: Sequence[str], labels: Mapping[str, str], profile: str,
                  source: str | Mapping[str, str], out: Mapping[str, str | Path]) -> pl.DataFrame:
    """Draw paper Fig. 11 and write it (PNG, PDF and the CSV of the numbers drawn).

    Args:
        histories: the DSWM histories of every dataset and seed drawn (``read_histories``).
        datasets: the datasets, in colour order; labels: {dataset: label}.
        out: {"png", "pdf", "csv"} paths.
    Returns:
        The CSV's table (:func:`summarize`).
    """
    table = summarize(histories)
    colors = dict(zip(datasets, plt.rcParams["axes.prop_cycle"].by_key()["color"]))
    fig, axes = plt.subplots(1, len(PANELS), figsize=(4.0 * len(PANELS), 3.6))
    for ax, (title, series, scale) in zip(axes, PANELS):
        for dataset in datasets:
            for (name, legend), style in zip(series, ("-", "--", ":")):
                rows = table.filter((pl.col("dataset") == dataset) & (pl.col("series") == name))
                if not rows.height:
                    continue
                x, y, s = (rows[c].to_numpy() for c in ("step", "value", "value_std"))
                label = labels.get(dataset, dataset) + (f" ({legend})" if len(series) > 1 else "")
                ax.plot(x, y, style, color=colors[dataset], lw=1.2, label=label)
                if bool((rows["seeds"] > 1).any()):
                    lo = np.maximum(y - s, y * 1e-3) if scale == "log" else y - s
                    ax.fill_between(x, lo, y + s, color=colors[dataset], alpha=0.2, lw=0)
        ax.set_yscale(scale)
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("gradient step")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    seeds = ", ".join(f"{labels.get(d, d)}: {histories.filter(pl.col('dataset') == d)['seed'].n_unique()}"
                      for d in datasets)
    fig.suptitle(f"DSWM training diagnostics (seeds per dataset: {seeds})", fontsize=11)
    fig.tight_layout(rect=(0, 0.05, 1, 0.95))
    save_figure(fig, table, **out, profile=profile, source=source, caption=CAPTION)
    return table
