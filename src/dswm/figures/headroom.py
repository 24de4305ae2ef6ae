"""Figure ``headroom`` (no paper figure): where foresight could pay. On each dataset of
``figures.headroom``, Greedy, Perfect forecast and the per-slot Ceiling over D_max x demand intensity (u x factor):
(a) Perfect - Greedy, the room a forecast could fill, and (b) Ceiling - Perfect, what the motion limit costs, per
cell. The scenario's own cell (its D_max, u x 1) is the main evaluations cut to the map's days; the others are
extra runs (``D<metres>[u<factor>]``); the ceiling has no motion limit, so one run per factor serves every D_max."""
from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import polars as pl

from dswm.figures.common import plt, save_figure
from dswm.figures.variants import check_same_days, first_days
from dswm.settings import EvalDayLimits

CAPTION = ("Headroom (no paper figure): per D_max (largest move per slot) and demand intensity (u x factor), (a) Perfect "
           "forecast - Greedy, the room a forecast could fill, and (b) Ceiling - Perfect, what the motion limit "
           "costs; served ratio, mean over seeds of each seed's mean day; outlined: room >= {min_room:g}.")


def _per_seed(rows: pl.DataFrame) -> pl.DataFrame:
    return rows.group_by(["split", "seed"]).agg(pl.col("sr_mean").mean())


def headroom_table(main: pl.DataFrame, runs: pl.DataFrame | None, *, datasets: Sequence[str],
                   d_max_m: Sequence[float], intensity_scales: Sequence[float], own_d_max: float,
                   seeds: Mapping[str, Sequence[int]], limits: EvalDayLimits, min_room: float,
                   names: Mapping[tuple[float, float], str | None]) -> pl.DataFrame:
    """The map's numbers: one row per (dataset, split, D_max, factor).

    Args:
        main: main evaluations' rows (dataset, method, seed, split, day, sr_mean) of greedy, perfect and ceiling.
        runs: the map's extra runs' rows (their ``variant`` column), or None.
        datasets, d_max_m, intensity_scales: the map (``figures.headroom``); own_d_max: the scenario's D_max.
        seeds: {dataset: the seeds of the map there}; limits: the map's day limits.
        min_room: a cell whose room reaches it is named (column ``named``, ``regime``).
        names: {(D_max, factor): the run's variant name, None for the scenario's own cell}
            (``dswm.settings.headroom_variant``).
    Returns:
        dataset, split, d_max_m, factor, greedy, perfect, ceiling (served ratios, null where not run), room
        (perfect - greedy), motion_cost (ceiling - perfect), share_ceiling_room (room / (ceiling - greedy)),
        named (room >= min_room), regime ("milan, D_max 250 m, u x 2" where named, else null), seeds, days.
    Raises:
        ValueError: an extra run covers other days than the main reference, or a needed run is missing.
    """
    runs = runs if runs is not None and runs.height else pl.DataFrame(
        schema={"dataset": pl.String, "variant": pl.String, "method": pl.String, "seed": pl.Int32,
                "split": pl.String, "day": pl.Int32, "sr_mean": pl.Float64})
    rows = []
    for dataset in datasets:
        seed_list = list(seeds[dataset])
        ref_main = main.filter((pl.col("dataset") == dataset) & pl.col("seed").is_in(seed_list))
        ref_main = first_days(ref_main, limits) if ref_main.height else ref_main
        on_ds = runs.filter((pl.col("dataset") == dataset) & pl.col("seed").is_in(seed_list))

        def cell(method: str, d: float, f: float) -> pl.DataFrame:
            name = names[(float(d), float(f))]
            if name is None:
                return ref_main.filter(pl.col("method") == method)
            part = on_ds.filter((pl.col("method") == method) & (pl.col("variant") == name))
            if not part.height and method in set(main["method"].to_list()):
                raise ValueError(f"headroom: no extra run {name} of {method} on {dataset} (seeds {seed_list}); "
                                 f"expected results/extra/{dataset}/{name}/{method}/seed<seed>/days.parquet")
            reference = ref_main.filter(pl.col("method") == "greedy")
            if part.height and reference.height:
                check_same_days(reference, part, f"headroom {dataset} {name}/{method}")
            return part

        for f in intensity_scales:
            ceiling = _per_seed(cell("ceiling", own_d_max, f))
            for d in d_max_m:
                greedy, perfect = _per_seed(cell("greedy", d, f)), _per_seed(cell("perfect", d, f))
                for split in sorted(set(greedy["split"].to_list()) | set(perfect["split"].to_list())):
                    vals = {}
                    for name, frame in (("greedy", greedy), ("perfect", perfect), ("ceiling", ceiling)):
                        s = frame.filter(pl.col("split") == split)["sr_mean"]
                        vals[name] = float(s.mean()) if s.len() else None
                    n_days = cell("greedy", d, f).filter(pl.col("split") == split).group_by("seed").len()
                    rows.append({"dataset": dataset, "split": split, "d_max_m": float(d), "factor": float(f),
                                 **vals, "seeds": greedy.filter(pl.col("split") == split).height,
                                 "days": int(n_days["len"].max()) if n_days.height else 0})
    table = pl.DataFrame(rows, schema={"dataset": pl.String, "split": pl.String, "d_max_m": pl.Float64,
                                       "factor": pl.Float64, "greedy": pl.Float64, "perfect": pl.Float64,
                                       "ceiling": pl.Float64, "seeds": pl.Int64, "days": pl.Int64})
    room = pl.col("perfect") - pl.col("greedy")
    table = table.with_columns(room.alias("room"), (pl.col("ceiling") - pl.col("perfect")).alias("motion_cost"),
                               pl.when(pl.col("ceiling") != pl.col("greedy"))
                               .then(room / (pl.col("ceiling") - pl.col("greedy"))).otherwise(None)
                               .alias("share_ceiling_room"))
    named = (table["room"].fill_null(-1.0) >= float(min_room)).to_list()
    regimes = [f"{r['dataset']}, D_max {r['d_max_m']:g} m, u x {r['factor']:g}" if ok else None
               for r, ok in zip(table.iter_rows(named=True), named)]
    return table.with_columns(pl.Series("named", named, dtype=pl.Boolean), pl.Series("regime", regimes,
                                                                                      dtype=pl.String))


def draw_headroom(table: pl.DataFrame, *, min_room: float, dataset_labels: Mapping[str, str], profile: str,
                  source: str | Mapping[str, str], out: Mapping[str, str | Path]) -> pl.DataFrame:
    """Draw the map (first split present per dataset) and write it (PNG, PDF and the CSV, :func:`headroom_table`,
    its caption listing the named regimes).

    Returns:
        ``table`` as written.
    """
    datasets = list(dict.fromkeys(table["dataset"].to_list()))
    fig, axes = plt.subplots(2, max(1, len(datasets)), figsize=(4.8 * max(1, len(datasets)), 7.4), squeeze=False)
    for j, dataset in enumerate(datasets):
        part = table.filter(pl.col("dataset") == dataset)
        split = part["split"][0]
        part = part.filter(pl.col("split") == split)
        ds, fs = sorted(set(part["d_max_m"].to_list())), sorted(set(part["factor"].to_list()))
        for i, (column, title) in enumerate((("room", "Perfect - Greedy (room)"),
                                             ("motion_cost", "Ceiling - Perfect (motion limit)"))):
            grid = np.full((len(fs), len(ds)), np.nan)
            for r in part.iter_rows(named=True):
                if r[column] is not None:
                    grid[fs.index(r["factor"]), ds.index(r["d_max_m"])] = r[column]
            ax = axes[i, j]
            lim = max(0.02, float(np.nanmax(np.abs(grid)))) if np.isfinite(grid).any() else 0.02
            im = ax.imshow(grid, cmap="RdBu_r" if column == "room" else "Oranges", origin="lower",
                           vmin=-lim if column == "room" else 0.0, vmax=lim, aspect="auto")
            for (a, b), v in np.ndenumerate(grid):
                dark = not np.isnan(v) and abs(v) > 0.6 * lim
                ax.text(b, a, "--" if np.isnan(v) else f"{v:+.3f}", ha="center", va="center", fontsize=8,
                        color="white" if dark else "black")
                if column == "room" and not np.isnan(v) and v >= min_room:
                    ax.add_patch(plt.Rectangle((b - 0.5, a - 0.5), 1, 1, fill=False, ec="k", lw=2))
            ax.set_xticks(range(len(ds)), [f"{d:g}" for d in ds])
            ax.set_yticks(range(len(fs)), [f"{f:g}" for f in fs])
            ax.set_xlabel("D_max (m per slot)")
            ax.set_ylabel("demand intensity (x u)")
            ax.set_title(f"({'ab'[i]}) {dataset_labels.get(dataset, dataset)}: {title}, {split}", fontsize=9)
            fig.colorbar(im, ax=ax, fraction=0.046)
    fig.tight_layout(rect=(0, 0.06, 1, 0.97))
    regimes = [r for r in table["regime"].to_list() if r is not None]
    caption = CAPTION.format(min_room=min_room) + (
        f" Room >= {min_room:g} in: {'; '.join(regimes)}." if regimes else f" No regime reaches room {min_room:g}.")
    save_figure(fig, table, **out, profile=profile, source=source, caption=caption)
    return table
