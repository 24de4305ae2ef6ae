"""Exploratory statistics of a prepared dataset (the paper's EDA figure): JSON and a two-panel PNG."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from prep import stats
from prep.atomic import atomic_path, write_json
from prep.tensor import DemandTensor

# Hotspot migration (`migration_window`, stats.hotspot_migration): 51 slots (8 h 30 min) from the window's first
# slot, pairs of share maps 18 slots (3 h) apart. Milan's window is the one of the real full-grid frames
# shipped with the demo (2013-11-03 00:00-08:20 local; docs/DATA.md gives their figures), so the demo and real
# data are compared on the same slots; a dataset without such a window, or a Milan tensor without that day,
# uses the first training day from 00:00.
MIGRATION_SLOTS = 51
MIGRATION_LAG = 18
REFERENCE_WINDOWS = {"milan": ("2013-11-03", 0)}  # dataset -> (day label, first slot)


def migration_window(t: DemandTensor) -> dict:
    """The window of the hotspot-migration figures of a tensor.

    Returns:
        dict with day (label), day_index, first_slot, slots and basis ("real frames' window" or
        "first training day").
    """
    days = t.meta["days"]
    ref = REFERENCE_WINDOWS.get(t.meta["dataset"])
    match = [d for d in days if ref is not None and d["label"] == ref[0]]
    if match and ref[1] + MIGRATION_SLOTS <= t.demand.shape[1]:
        day, first, basis = match[0], ref[1], "real frames' window"
    else:
        day, first, basis = next((d for d in days if d["split"] == "train"), days[0]), 0, "first training day"
    return {"day": day["label"], "day_index": int(day["index"]), "first_slot": int(first),
            "slots": MIGRATION_SLOTS, "basis": basis}


def hotspot_migration(t: DemandTensor, top_frac: float) -> dict:
    """Hotspot-migration figures of a tensor on `migration_window`.

    Returns:
        dict with window (see `migration_window`), lag_slots, top_k (max(1, round(top_frac x cells)): 20 of
        Milan's 400), top_k_share_overlap (mean overlap of the top-k cells of share maps lag_slots apart; 1 =
        hotspots stay put) and energy_outside_first_component (1 - s1^2 / sum s_i^2 of the window's frames x
        cells matrix; 0 = one map, scaled).
    """
    w = migration_window(t)
    frames = t.demand[w["day_index"], w["first_slot"]: w["first_slot"] + w["slots"]]
    k = max(1, int(round(top_frac * frames[0].size)))
    return {"window": w, "lag_slots": MIGRATION_LAG, "top_k": k,
            **stats.hotspot_migration(frames, k, MIGRATION_LAG)}


def eda_stats(t: DemandTensor, *, top_frac: float = 0.05) -> dict:
    """Statistics of a prepared dataset.

    Args:
        t: the loaded tensor (demand (D, 144, R, C)).
        top_frac: fraction of cells in the top-cell share.
    Returns:
        dict with zero_cell_rate, top5_share, daily_cycle {weekday, weekend} (144 mean crop totals per slot
        each), daily_totals [{index, label, split, eval, total}], hotspot_overlap_04h_14h (overlap of the
        top cells at 04:00 and 14:00; 1 = hotspots stay put), hotspot_migration (`hotspot_migration`) and the
        meta figures p99, kappa, week.
    """
    d = t.demand
    weekend = np.array([day["weekend"] for day in t.meta["days"]])
    ood, idd = set(t.meta["eval_days"]["ood"]), set(t.meta["eval_days"]["id"])
    totals = stats.daily_totals(d)
    wk, we = stats.daily_cycle(d, ~weekend), stats.daily_cycle(d, weekend)
    return {
        "dataset": t.meta["dataset"],
        "source": t.meta["source"],
        "shape": list(d.shape),
        "zero_cell_rate": stats.zero_cell_rate(d),
        "top5_share": stats.top_share(d, top_frac),
        "hotspot_overlap_04h_14h": stats.hotspot_motion(d, top_frac),
        "hotspot_migration": hotspot_migration(t, top_frac),
        "daily_cycle": {"weekday": wk.tolist(), "weekend": we.tolist(),
                        "weekday_peak_slot": int(np.argmax(wk)), "weekend_peak_slot": int(np.argmax(we)) if we.any()
                        else None},
        "daily_totals": [{"index": day["index"], "label": day["label"], "split": day["split"],
                          "eval": "ood" if day["index"] in ood else "id" if day["index"] in idd else None,
                          "total": float(totals[day["index"]])} for day in t.meta["days"]],
        "p99": t.meta["p99"],
        "kappa": t.meta["kappa"],
        "week": t.meta["week"],
    }


def eda_figure(summary: dict, path: Path | str) -> None:
    """Writes the two-panel EDA figure (daily cycle weekday vs weekend; daily totals with split and OOD days)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 3.6))
    hours = np.arange(144) / 6.0
    weekend_label = "pseudo-weekend" if summary["dataset"] == "yjmob" else "weekend"
    ax1.plot(hours, summary["daily_cycle"]["weekday"], label="weekday")
    ax1.plot(hours, summary["daily_cycle"]["weekend"], label=weekend_label)
    ax1.set_xlabel("hour of day")
    ax1.set_ylabel("crop demand per slot (normalized x kappa)")
    ax1.set_xlim(0, 24)
    ax1.legend()
    ax1.set_title(f"{summary['dataset']}: daily cycle")
    rows = summary["daily_totals"]
    x = np.arange(len(rows))
    colours = ["tab:red" if r["eval"] == "ood" else "tab:green" if r["eval"] == "id" else
               ("tab:blue" if r["split"] == "train" else "tab:gray") for r in rows]
    ax2.bar(x, [r["total"] for r in rows], color=colours, width=0.85)
    n_train = sum(r["split"] == "train" for r in rows)
    ax2.axvline(n_train - 0.5, color="k", linestyle="--", linewidth=1)
    ax2.set_xlabel("day (blue train, gray test, green ID eval, red OOD eval)")
    ax2.set_ylabel("daily total")
    step = max(1, len(rows) // 8)
    ax2.set_xticks(x[::step], [r["label"] for r in rows][::step], rotation=30, fontsize=7)
    ax2.set_title(f"zero cells {summary['zero_cell_rate']:.1%}, top 5% share {summary['top5_share']:.1%}")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=120)
    plt.close(fig)


def run_eda(t: DemandTensor, *, json_path: Path | str, png_path: Path | str, top_frac: float) -> dict:
    """Computes the statistics and writes both outputs; returns the statistics."""
    summary = eda_stats(t, top_frac=top_frac)
    eda_figure(summary, png_path)
    write_json(json_path, summary)
    return summary
