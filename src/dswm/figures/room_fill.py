"""Figure ``room_fill`` (no paper figure): DSWM+ where the room is. In one regime of the headroom map
(``figures.room_fill``), the share of the room (Perfect - Greedy) that each planner fills, per split:
(SR - Greedy) / (Perfect - Greedy), with Greedy and Perfect on the same days and seeds. The candidate is DSWM+ with
anchoring per imagined step rho_k and a gamma chosen on training days (``dswm.pipeline.room_fill``); its fitted rho_k
are drawn beside the shares."""
from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import polars as pl

from dswm.figures.common import mean_std, plt, save_figure

LOW, HIGH = "greedy", "perfect"
"""The arms that bound the room: planning on the current map, and on the true future maps."""
CAPTION = ("Room fill (no paper figure): DSWM+ where the room is, {regime}: share of the room (Perfect - Greedy) "
           "each planner fills, (SR - Greedy) / (Perfect - Greedy) on the same days and seeds, per split; right: the "
           "candidate's rho_k, fitted on training days.")


def room_fill_table(runs: pl.DataFrame, *, arms: Sequence[str], labels: Mapping[str, str],
                    regime: Mapping[str, float | str], split_labels: Mapping[str, str]) -> pl.DataFrame:
    """The figure's numbers: one row per (split, arm) and per arm over all days (split ``all``).

    Args:
        runs: the arms' per-day rows, column ``arm`` added (dataset, seed, split, day, sr_mean).
        arms: the arms in order (``greedy`` and ``perfect`` among them); labels: {arm: its label}.
        regime: {dataset, d_max_m, intensity_scale}; split_labels: {id, ood: column names of the tables}.
    Returns:
        dataset, d_max_m, intensity_scale, split, split_label, arm, label, sr, sr_std, greedy, perfect, room
        (perfect - greedy), share ((sr - greedy) / room; null where the room is not positive), seeds, days.
    Raises:
        ValueError: an arm misses Greedy's or Perfect's (seed, day) pairs, or they miss its.
    """
    for bound in (LOW, HIGH):
        if bound not in arms:
            raise ValueError(f"room_fill: the arm {bound!r} bounds the room and is missing (found {list(arms)})")
    keys = {a: set(runs.filter(pl.col("arm") == a).select("seed", "split", "day").iter_rows()) for a in arms}
    for a in arms:
        if keys[a] != keys[LOW]:
            raise ValueError(f"room_fill: arm {a!r} covers other (seed, split, day) than {LOW!r}: "
                             f"{sorted(keys[a] ^ keys[LOW])}; every arm must run the same days and seeds")
    both = pl.concat([runs, runs.with_columns(pl.lit("all").alias("split"))])
    stats = mean_std(both, ["split", "arm"], "sr_mean")
    days = both.group_by(["split", "arm"]).agg(pl.len().alias("days"))
    stats = stats.join(days, on=["split", "arm"])
    rows = []
    for split in [s for s in ("id", "ood", "all") if s in set(stats["split"])]:
        on = {r["arm"]: r for r in stats.filter(pl.col("split") == split).iter_rows(named=True)}
        low, high = on[LOW]["sr_mean"], on[HIGH]["sr_mean"]
        room = high - low
        for a in arms:
            r = on[a]
            rows.append({"dataset": regime["dataset"], "d_max_m": float(regime["d_max_m"]),
                         "intensity_scale": float(regime["intensity_scale"]), "split": split,
                         "split_label": split_labels.get(split, "All days"), "arm": a, "label": labels[a],
                         "sr": r["sr_mean"], "sr_std": r["sr_mean_std"], "greedy": low, "perfect": high, "room": room,
                         "share": (r["sr_mean"] - low) / room if room > 0 else None, "seeds": r["seeds"],
                         "days": r["days"] // max(r["seeds"], 1)})
    return pl.DataFrame(rows)


def draw_room_fill(table: pl.DataFrame, fits: Sequence[Mapping], *, profile: str, source: str,
                   out: Mapping[str, str | Path]):
    """Draw the shares per split (left) and the candidate's rho_k with the forecast RMSE per step (right); write
    the PNG, PDF and the table as CSV."""
    regime = table.row(0, named=True)
    arms = [a for a in dict.fromkeys(table["arm"]) if a not in (LOW, HIGH)]
    splits = list(dict.fromkeys(table["split"]))
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4))
    width = 0.8 / max(len(splits), 1)
    for i, split in enumerate(splits):
        sub = {r["arm"]: r for r in table.filter(pl.col("split") == split).iter_rows(named=True)}
        vals = [np.nan if sub[a]["share"] is None else sub[a]["share"] for a in arms]
        label = f"{sub[arms[0]]['split_label']} (room {sub[arms[0]]['room']:+.3f})"
        ax.bar(np.arange(len(arms)) + (i - (len(splits) - 1) / 2) * width, vals, width, label=label)
    ax.axhline(0.0, color="k", lw=0.8)
    ax.axhline(1.0, color="k", lw=0.8, ls=":")
    ax.axhline(0.5, color="tab:red", lw=0.8, ls="--")
    labels = dict(zip(table["arm"], table["label"]))
    ax.set_xticks(np.arange(len(arms)), [labels[a] for a in arms], rotation=20, ha="right", fontsize=8)
    ax.set_ylabel("share of the room filled")
    ax.legend(fontsize=7)
    for fit in fits:
        k = np.arange(1, len(fit["rho_steps"]) + 1)
        bx.plot(k, fit["rho_steps"], "o-", label=f"rho_k (seed {fit['seed']}), gamma {fit['gamma']:g}")
        bx.axhline(fit["rho_fixed"], color="grey", ls=":", label=f"rho {fit['rho_fixed']:g} (DSWM+)")
    bx.set_xlabel("imagined step k")
    bx.set_ylabel("rho_k (1: persistence, 0: model)")
    bx.set_ylim(-0.05, 1.05)
    bx.legend(fontsize=7)
    name = f"{regime['dataset']}, D_max {regime['d_max_m']:g} m, u x {regime['intensity_scale']:g}"
    fig.suptitle(f"DSWM+ where the room is: {name} ({profile})", fontsize=10)
    fig.subplots_adjust(bottom=0.34, wspace=0.25)  # the arms' labels, then the caption below them
    save_figure(fig, table, **out, profile=profile, source=source, caption=CAPTION.format(regime=name))


__all__ = ["CAPTION", "draw_room_fill", "room_fill_table"]
