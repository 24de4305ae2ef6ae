"""Paper Fig. 12 (world-model quality on the test period): (a) demand RMSE against the imagination step, (b) the
imagined against the realized return of every (seed, evaluated day), with Spearman's r_s.

Drawn from the world-model quality job's files (``results/extra/<dataset>/wm_quality/seed<seed>/rmse.parquet`` and
``returns.parquet``, ``dswm.pipeline.wm``): the DSWM controller replayed on the main evaluation's days, its model
imagining open loop along the executed actions (``dswm.methods.dswm.quality``)."""
from __future__ import annotations

import math
from pathlib import Path
from typing import Mapping

import numpy as np
import polars as pl
from scipy.stats import spearmanr

from dswm.figures.common import plt, save_figure

RMSE_SERIES = (("mse_model", "world model (ensemble mean)", "-"),
               ("mse_anchored", "planner's anchored map", "--"),
               ("mse_persistence", "persistence x_t", ":"))
"""The curves of panel (a): the rmse.parquet column, its legend and line style."""
MIN_RANK_POINTS = 3
"""Fewest points a Spearman correlation is computed on (with two, r_s is +-1 whatever the data)."""
CAPTION = ("Paper Fig. 12 (wm_quality): world-model quality on the test period. (a) demand RMSE against the "
           "imagination step, open loop from the posterior at every slot along the executed actions (mean ± std "
           "over seeds); (b) imagined (the planner's first-step SR_hat of each executed action) against realized "
           "served ratio, mean over a day's decisions, one point per seed-day pair, with Spearman r_s.")


def rmse_table(rmse: pl.DataFrame) -> pl.DataFrame:
    """Per (step, series): RMSE in normalized units and Mbps, mean over seeds of each seed's RMSE (the root of its
    mean squared error over days, starts and cells), the std over seeds (0 for one seed) and the seed count.

    Args:
        rmse: rows of rmse.parquet (seed, day, step, starts, mse_*, mbps_per_unit).
    """
    long = rmse.unpivot(index=["seed", "day", "step", "starts", "mbps_per_unit"],
                        on=[c for c, _, _ in RMSE_SERIES], variable_name="series", value_name="mse")
    per_seed = (long.group_by(["series", "step", "seed"], maintain_order=True)
                .agg(((pl.col("mse") * pl.col("starts")).sum() / pl.col("starts").sum()).sqrt().alias("rmse"),
                     pl.col("mbps_per_unit").first()))
    table = (per_seed.group_by(["series", "step"], maintain_order=True)
             .agg(pl.col("rmse").mean(), pl.col("rmse").std(ddof=0).fill_null(0.0).alias("rmse_std"),
                  pl.col("mbps_per_unit").first(), pl.len().alias("seeds")))
    return (table.with_columns((pl.col("rmse") * pl.col("mbps_per_unit")).alias("rmse_mbps"),
                               (pl.col("rmse_std") * pl.col("mbps_per_unit")).alias("rmse_mbps_std"))
            .with_columns(pl.col("series").str.replace("^mse_", ""))
            .sort(["series", "step"], maintain_order=True))


def rank_correlation(returns: pl.DataFrame) -> dict[str, float | int]:
    """Spearman r_s between imagined and realized return: over every (seed, day) point ("r_s") and per seed over
    its days, mean and std over the seeds that have at least :data:`MIN_RANK_POINTS` days ("r_s_seed_mean",
    "r_s_seed_std", "seeds_ranked"); NaN where too few points (or no variation) leave it undefined."""
    def rho(frame: pl.DataFrame) -> float:
        if frame.height < MIN_RANK_POINTS:
            return math.nan
        x, y = frame["imagined_sr"].to_numpy(), frame["realized_sr"].to_numpy()
        if np.ptp(x) == 0 or np.ptp(y) == 0:
            return math.nan
        return float(spearmanr(x, y).statistic)

    per_seed = [rho(part) for _, part in returns.group_by("seed", maintain_order=True)]
    ranked = [r for r in per_seed if not math.isnan(r)]
    return {"r_s": rho(returns), "points": returns.height,
            "r_s_seed_mean": float(np.mean(ranked)) if ranked else math.nan,
            "r_s_seed_std": float(np.std(ranked)) if ranked else math.nan, "seeds_ranked": len(ranked)}


def _fmt(v: float) -> str:
    return "n/a" if math.isnan(v) else f"{v:.3f}"


def draw_wm_quality(rmse: pl.DataFrame, returns: pl.DataFrame, *, dataset_label: str, profile: str, source: str,
                    out: Mapping[str, str | Path]) -> pl.DataFrame:
    """Draw paper Fig. 12 and write it (PNG, PDF and the CSV of the numbers drawn).

    Args:
        rmse, returns: the rows of every seed's rmse.parquet and returns.parquet.
        out: {"png", "pdf", "csv"} paths.
    Returns:
        The CSV's table: panel "a" rows (:func:`rmse_table`), panel "b" rows (one per seed-day: seed, day, label,
        split, imagined_sr, realized_sr) and one panel "b" summary row (series "spearman": r_s, points and the
        per-seed mean and std).
    """
    table = rmse_table(rmse)
    ranks = rank_correlation(returns)
    fig, (ax_a, ax_b) = plt.subplots(1, 2, figsize=(10.5, 4.3))
    mbps = bool(table["mbps_per_unit"].is_not_null().all())
    for column, legend, style in RMSE_SERIES:
        rows = table.filter(pl.col("series") == column[4:])
        x = rows["step"].to_numpy()
        y, s = (rows["rmse_mbps"], rows["rmse_mbps_std"]) if mbps else (rows["rmse"], rows["rmse_std"])
        ax_a.plot(x, y.to_numpy(), style, marker="o", ms=3, label=legend)
        if bool((rows["seeds"] > 1).any()):
            ax_a.fill_between(x, (y - s).to_numpy(), (y + s).to_numpy(), alpha=0.2, lw=0)
    ax_a.set_xlabel("imagination step k (slots)")
    ax_a.set_ylabel("demand RMSE per cell (Mbps requested)" if mbps else "demand RMSE (normalized units)")
    ax_a.set_title(f"(a) demand RMSE vs. imagination step, {dataset_label}", fontsize=10)
    ax_a.grid(alpha=0.3)
    ax_a.legend(fontsize=8)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    markers = {"id": "o", "ood": "s"}
    for i, (seed, part) in enumerate(returns.sort(["seed", "day"]).group_by("seed", maintain_order=True)):
        for split, rows in part.group_by("split", maintain_order=True):
            ax_b.scatter(rows["imagined_sr"], rows["realized_sr"], color=colors[i % len(colors)],
                         marker=markers.get(split[0], "^"), s=28, label=f"seed {seed[0]} ({split[0]})")
    lo = float(min(returns["imagined_sr"].min(), returns["realized_sr"].min()))
    hi = float(max(returns["imagined_sr"].max(), returns["realized_sr"].max()))
    pad = max(0.01, 0.05 * (hi - lo))
    ax_b.plot([lo - pad, hi + pad], [lo - pad, hi + pad], color="0.5", ls=":", lw=0.8)
    ax_b.set_xlabel("imagined return (mean SR_hat per decision)")
    ax_b.set_ylabel("realized return (mean SR per decision)")
    per_seed = (f"; per seed {_fmt(ranks['r_s_seed_mean'])} ± {_fmt(ranks['r_s_seed_std'])} "
                f"({ranks['seeds_ranked']} seeds)" if ranks["seeds_ranked"] else "")
    ax_b.set_title(f"(b) r_s = {_fmt(ranks['r_s'])} over {ranks['points']} seed-days{per_seed}", fontsize=10)
    ax_b.grid(alpha=0.3)
    ax_b.legend(fontsize=7)
    fig.tight_layout(rect=(0, 0.07, 1, 0.97))
    points = returns.select("seed", "day", "label", "split", "imagined_sr", "realized_sr").with_columns(
        pl.lit("b").alias("panel"), pl.lit("seed-day").alias("series"))
    summary = pl.DataFrame({"panel": ["b"], "series": ["spearman"], "r_s": [ranks["r_s"]],
                            "points": [ranks["points"]], "r_s_seed_mean": [ranks["r_s_seed_mean"]],
                            "r_s_seed_std": [ranks["r_s_seed_std"]], "seeds_ranked": [ranks["seeds_ranked"]]})
    data = pl.concat([table.with_columns(pl.lit("a").alias("panel")), points, summary], how="diagonal_relaxed")
    data = data.select("panel", "series", *[c for c in data.columns if c not in ("panel", "series")])
    save_figure(fig, data, **out, profile=profile, source=source, caption=CAPTION)
    return data
