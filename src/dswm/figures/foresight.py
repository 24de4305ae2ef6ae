"""Figure ``foresight`` (no paper figure): demand source x planner. (a) per dataset, the served ratio of
Algorithm 1's planner (``dswm``'s) and of DSWM+'s, each on persistence, on the world model anchored by the
planner's own rho and by ``figures.foresight.rho``, and on the true future maps, with Greedy and Perfect forecast
as lines; (b) the world model's demand RMSE against persistence's per imagination step (the ``wm_quality``
replay). A cell that is a method's main evaluation is that file cut to the grid's days; the others are extra runs
(``rho<r>``, ``alg1``) with the same trained model."""
from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence

import polars as pl

from dswm.figures.common import mean_std, plt, save_figure
from dswm.figures.variants import check_same_days, first_days
from dswm.figures.wm_quality import rmse_table
from dswm.settings import EvalDayLimits

PLANNER_LABELS = {"alg1": "Algorithm 1 (dswm's planner)", "plus": "DSWM+'s planner"}
CAPTION = ("Foresight (no paper figure): (a) served ratio per demand source x planner (persistence; world model anchored "
           "by rho; true future maps), mean over seeds of each seed's mean day, with Greedy (dashed) and Perfect "
           "forecast (dotted); 'not run': a method the profile does not evaluate there; (b) the world model's "
           "demand RMSE (rho 0: the ensemble mean; anchored: rho 0.95) against persistence's per imagination step, "
           "on the wm_quality replay's days.")


GIVEN_MAPS = "given maps: no anchoring (rho does not apply) and no uncertainty term"
NOT_RUN = "not run: the profile does not evaluate this cell's method (or dswm, whose planner it takes) here"


def source_label(source: str, rho: float | None) -> str:
    """The x-axis label of a demand source: "persistence", "true maps" or "model, rho 0.95"."""
    if source == "model":
        return f"model, rho {rho:g}"
    return {"persistence": "persistence", "true": "true maps"}.get(source, source)


def _cut(main: pl.DataFrame, dataset: str, methods: Sequence[str], seeds: Sequence[int],
         limits: EvalDayLimits) -> pl.DataFrame:
    part = main.filter((pl.col("dataset") == dataset) & pl.col("method").is_in(list(methods))
                       & pl.col("seed").is_in(list(seeds)))
    return first_days(part, limits) if part.height else part


def _mean(rows: pl.DataFrame) -> tuple[float | None, float | None, int, int]:
    """(mean over seeds of each seed's mean sr_mean, std over seeds (0 for one), seeds, days per seed)."""
    if not rows.height:
        return None, None, 0, 0
    stats = mean_std(rows, [], "sr_mean").row(0, named=True)
    days = int(rows.group_by("seed").len()["len"].max())
    return float(stats["sr_mean"]), float(stats["sr_mean_std"]), stats["seeds"], days


def foresight_table(main: pl.DataFrame, runs: pl.DataFrame | None, cells: Mapping[str, Sequence[Mapping]], *,
                    seeds: Mapping[str, Sequence[int]], limits: EvalDayLimits) -> pl.DataFrame:
    """The grid's numbers, one row per (dataset, planner, source, rho) cell and per dataset a Greedy and a Perfect
    row (planner "reference").

    Args:
        main: main evaluations' rows (dataset, method, seed, split, day, sr_mean) of the cells' methods, greedy and
            perfect on the grid's datasets.
        runs: the grid's extra runs' rows (with ``variant``), or None.
        cells: {dataset: cells of ``dswm.settings.foresight_cells``, ``variant`` as its name or None}.
        seeds: {dataset: the seeds of the grid there}; limits: the grid's day limits (``figures.foresight``).
    Returns:
        dataset, planner, source, rho, method, variant (null: the main evaluation), status ("main", "extra" or
        "not run"), note (why rho is empty, or why a cell did not run), sr_mean, sr_mean_std, seeds, days (per seed), greedy_sr, perfect_sr, vs_greedy (sr_mean -
        greedy_sr) and share_of_room ((sr_mean - greedy) / (perfect - greedy), null where the room is 0).
    Raises:
        ValueError: an extra run covers other days than its main reference, or a cell's run is missing.
    """
    runs = runs if runs is not None and runs.height else None
    rows = []
    for dataset, grid in cells.items():
        ref = _cut(main, dataset, ["greedy", "perfect"], seeds[dataset], limits)
        greedy = _mean(ref.filter(pl.col("method") == "greedy"))
        perfect = _mean(ref.filter(pl.col("method") == "perfect"))
        for name, value in (("greedy", greedy), ("perfect", perfect)):
            rows.append({"dataset": dataset, "planner": "reference", "source": name, "rho": None, "method": name,
                         "variant": None, "status": "main" if value[2] else "not run", "sr_mean": value[0],
                         "sr_mean_std": value[1], "seeds": value[2], "days": value[3]})
        for cell in grid:
            base = {k: cell[k] for k in ("planner", "source", "rho", "method", "variant")}
            if cell["method"] is None:
                rows.append({"dataset": dataset, **base, "status": "not run", "sr_mean": None, "sr_mean_std": None,
                             "seeds": 0, "days": 0})
                continue
            if cell["variant"] is None:
                part, status = _cut(main, dataset, [cell["method"]], seeds[dataset], limits), "main"
            else:
                part = pl.DataFrame() if runs is None else runs.filter(
                    (pl.col("dataset") == dataset) & (pl.col("method") == cell["method"])
                    & (pl.col("variant") == cell["variant"]) & pl.col("seed").is_in(list(seeds[dataset])))
                status = "extra"
                if not part.height:
                    raise ValueError(f"foresight: no extra run {cell['variant']} of {cell['method']} on {dataset} "
                                     f"(seeds {list(seeds[dataset])}); expected results/extra/{dataset}/"
                                     f"{cell['variant']}/{cell['method']}/seed<seed>/days.parquet")
                if ref.height:
                    check_same_days(ref.filter(pl.col("method") == "greedy"), part,
                                    f"foresight {dataset} {cell['variant']}/{cell['method']}")
            mean, std, n_seeds, n_days = _mean(part)
            rows.append({"dataset": dataset, **base, "status": status, "sr_mean": mean, "sr_mean_std": std,
                         "seeds": n_seeds, "days": n_days})
    table = pl.DataFrame(rows, schema={"dataset": pl.String, "planner": pl.String, "source": pl.String,
                                       "rho": pl.Float64, "method": pl.String, "variant": pl.String,
                                       "status": pl.String, "sr_mean": pl.Float64, "sr_mean_std": pl.Float64,
                                       "seeds": pl.Int64, "days": pl.Int64})
    notes = {"persistence": GIVEN_MAPS, "true": GIVEN_MAPS}
    table = table.with_columns(
        pl.when(pl.col("status") == "not run").then(pl.lit(NOT_RUN))
        .when(pl.col("planner") != "reference").then(pl.col("source").replace_strict(notes, default=None))
        .otherwise(None).alias("note"))
    refs = table.filter(pl.col("planner") == "reference").select(
        "dataset", pl.col("source"), "sr_mean").pivot(on="source", index="dataset", values="sr_mean")
    refs = refs.rename({c: f"{c}_sr" for c in refs.columns if c != "dataset"})
    for c in ("greedy_sr", "perfect_sr"):
        if c not in refs.columns:
            refs = refs.with_columns(pl.lit(None, dtype=pl.Float64).alias(c))
    room = pl.col("perfect_sr") - pl.col("greedy_sr")
    return (table.join(refs.select("dataset", "greedy_sr", "perfect_sr"), on="dataset", how="left",
                       maintain_order="left")
            .with_columns((pl.col("sr_mean") - pl.col("greedy_sr")).alias("vs_greedy"),
                          pl.when(room != 0).then((pl.col("sr_mean") - pl.col("greedy_sr")) / room)
                          .otherwise(None).alias("share_of_room")))


def draw_foresight(table: pl.DataFrame, rmse: Mapping[str, pl.DataFrame], *, dataset_labels: Mapping[str, str],
                   profile: str, source: str | Mapping[str, str], out: Mapping[str, str | Path]) -> pl.DataFrame:
    """Draw the figure and write it (PNG, PDF and the CSV of the numbers drawn).

    Args:
        table: :func:`foresight_table`; rmse: {dataset: the rows of its wm_quality rmse.parquet files} (a dataset
            without them gets no panel (b)); dataset_labels: {dataset: its name in titles}.
    Returns:
        The CSV's table: panel "a" (the grid, :func:`foresight_table`) and panel "b" rows (dataset, series, step,
        rmse, rmse_mbps: :func:`dswm.figures.wm_quality.rmse_table`).
    """
    datasets = list(dict.fromkeys(table["dataset"].to_list()))
    fig, axes = plt.subplots(2, len(datasets), figsize=(4.6 * len(datasets), 7.6), squeeze=False)
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    rmse_rows = []
    for j, dataset in enumerate(datasets):
        ax = axes[0, j]
        part = table.filter((pl.col("dataset") == dataset) & (pl.col("planner") != "reference"))
        keys = list(dict.fromkeys(zip(part["source"].to_list(), part["rho"].to_list())))
        planners = list(dict.fromkeys(part["planner"].to_list()))
        width = 0.8 / max(1, len(planners))
        for i, planner in enumerate(planners):
            for x, (src, rho) in enumerate(keys):
                row = part.filter((pl.col("planner") == planner) & (pl.col("source") == src)
                                  & (pl.col("rho").eq_missing(rho)))
                pos = x - 0.4 + width * (i + 0.5)
                if row["sr_mean"][0] is None:
                    ax.text(pos, 0.5, "not run", transform=ax.get_xaxis_transform(), rotation=90, ha="center",
                            va="center", fontsize=7, color="0.4")
                    continue
                ax.errorbar(pos, row["sr_mean"][0], yerr=row["sr_mean_std"][0] if row["seeds"][0] > 1 else None,
                            fmt="os"[i % 2], ms=7, color=colors[i], capsize=2,
                            label=PLANNER_LABELS.get(planner, planner) if x == 0 else None)
        refs = table.filter((pl.col("dataset") == dataset) & (pl.col("planner") == "reference"))
        for name, style in (("greedy", "--"), ("perfect", ":")):
            value = refs.filter(pl.col("source") == name)["sr_mean"]
            if value.len() and value[0] is not None:
                ax.axhline(value[0], color="0.2", ls=style, lw=1.0, label=name.capitalize() if j == 0 else None)
        shown = [v for v in part["sr_mean"].to_list() + refs["sr_mean"].to_list() if v is not None]
        if shown:
            lo, hi = min(shown), max(shown)
            ax.set_ylim(max(0.0, lo - 0.1 * (hi - lo + 0.01)), min(1.0, hi + 0.1 * (hi - lo + 0.01)) + 0.002)
        ax.set_xticks(range(len(keys)), [source_label(s, r) for s, r in keys], rotation=20, fontsize=8)
        ax.set_ylabel("served ratio")
        ax.set_title(f"(a) {dataset_labels.get(dataset, dataset)}", fontsize=10)
        ax.set_xlim(-0.6, len(keys) - 0.4)
        ax.grid(alpha=0.3, axis="y")
        if j == 0:
            ax.legend(fontsize=7)
        ax_b = axes[1, j]
        frame = rmse.get(dataset)
        if frame is None or not frame.height:
            ax_b.set_axis_off()
            ax_b.text(0.5, 0.5, "no wm_quality replay", ha="center", va="center", fontsize=9)
            continue
        curve = rmse_table(frame).with_columns(pl.lit(dataset).alias("dataset"))
        rmse_rows.append(curve)
        mbps = bool(curve["mbps_per_unit"].is_not_null().all())
        for series, legend, style in (("model", "world model, rho 0", "-"), ("anchored", "anchored, rho 0.95", "--"),
                                      ("persistence", "persistence", ":")):
            rows = curve.filter(pl.col("series") == series)
            ax_b.plot(rows["step"].to_numpy(), (rows["rmse_mbps"] if mbps else rows["rmse"]).to_numpy(), style,
                      marker="o", ms=2, label=legend)
        ax_b.set_xlabel("imagination step k (slots)")
        ax_b.set_ylabel("demand RMSE per cell" + (" (Mbps)" if mbps else ""))
        ax_b.set_title(f"(b) forecast error, {dataset_labels.get(dataset, dataset)}", fontsize=10)
        ax_b.grid(alpha=0.3)
        ax_b.legend(fontsize=7)
    fig.tight_layout(rect=(0, 0.05, 1, 0.97))
    data = table.with_columns(pl.lit("a").alias("panel"))
    if rmse_rows:
        data = pl.concat([data, pl.concat(rmse_rows, how="diagonal_relaxed").with_columns(pl.lit("b").alias("panel"))],
                         how="diagonal_relaxed")
    data = data.select("panel", *[c for c in data.columns if c != "panel"])
    save_figure(fig, data, **out, profile=profile, source=source, caption=CAPTION)
    return data
