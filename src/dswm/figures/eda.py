"""Paper Fig. 5 (eda): each dataset's daily demand cycle (weekday vs weekend) and daily totals across the
observation period with the train/test split and the evaluated days marked, from the `eda` rule's statistics."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Mapping

import numpy as np
import polars as pl

from dswm.figures.common import plt, save_figure
from dswm.protocol.tables import DATASET_LABELS


def read_stats(paths: Mapping[str, str | Path]) -> dict[str, dict]:
    """{dataset: the statistics the `eda` rule wrote (results/eda/<dataset>/eda.json)}."""
    out = {}
    for ds, p in paths.items():
        with open(p, encoding="utf-8") as fh:
            out[ds] = json.load(fh)
        for key in ("daily_cycle", "daily_totals", "zero_cell_rate", "top5_share"):
            if key not in out[ds]:
                raise ValueError(f"{p}: EDA statistics lack key {key!r}; expected the output of the eda rule "
                                 f"(re-run: snakemake --cores 2 results/eda/{ds}/eda.json)")
    return out


def draw_eda(stats: Mapping[str, dict], *, profile: str, out: Mapping[str, str | Path]) -> pl.DataFrame:
    """Two panels per dataset: (top) mean crop demand per slot over the day, weekday and weekend; (bottom) each
    day's total, coloured by split (train, test, ID and OOD evaluation days), the split boundary dashed.

    Returns (and writes as CSV) the long table drawn: dataset, panel ("cycle" or "daily"), x (hour or day index),
    label, series and value.
    """
    datasets = [d for d in DATASET_LABELS if d in stats]
    fig, axes = plt.subplots(2, len(datasets), figsize=(4.6 * len(datasets), 6.8), squeeze=False)
    rows = []
    hours = np.arange(144) / 6.0
    for j, ds in enumerate(datasets):
        s = stats[ds]
        weekend = "pseudo-weekend" if ds == "yjmob" else "weekend"
        ax = axes[0, j]
        for series, name in (("weekday", "weekday"), ("weekend", weekend)):
            values = s["daily_cycle"][series]
            ax.plot(hours[:len(values)], values, label=name)
            rows += [{"dataset": ds, "panel": "cycle", "x": float(h), "label": f"{h:.2f} h", "series": name,
                      "value": float(v)} for h, v in zip(hours, values)]
        ax.set_xlim(0, 24)
        ax.set_xlabel("hour of day")
        ax.set_title(f"{DATASET_LABELS[ds]}: zero cells {s['zero_cell_rate']:.1%}, top 5% share "
                     f"{s['top5_share']:.1%}", fontsize=9)
        ax.legend(fontsize=7)
        if j == 0:
            ax.set_ylabel("crop demand per slot (normalized × κ)")
        ax = axes[1, j]
        days = s["daily_totals"]
        kind = ["ood" if d["eval"] == "ood" else "id" if d["eval"] == "id" else d["split"] for d in days]
        colour = {"ood": "tab:red", "id": "tab:green", "train": "tab:blue"}
        ax.bar(np.arange(len(days)), [d["total"] for d in days], color=[colour.get(k, "tab:gray") for k in kind],
               width=0.85)
        ax.axvline(sum(d["split"] == "train" for d in days) - 0.5, color="k", ls="--", lw=1)
        step = max(1, len(days) // 6)
        ax.set_xticks(np.arange(len(days))[::step], [d["label"] for d in days][::step], rotation=30, fontsize=6)
        ax.set_xlabel("day (blue train, gray test, green ID eval, red OOD eval)", fontsize=7)
        if j == 0:
            ax.set_ylabel("daily total")
        rows += [{"dataset": ds, "panel": "daily", "x": float(d["index"]), "label": d["label"], "series": k,
                  "value": float(d["total"])} for d, k in zip(days, kind)]
    fig.tight_layout(rect=(0, 0.03, 1, 0.97))
    data = pl.DataFrame(rows)
    save_figure(fig, data, **out, profile=profile, source={DATASET_LABELS[d]: stats[d]["source"] for d in datasets},
                caption="Paper Fig. 5 (eda): daily demand cycle (weekday vs weekend) and daily totals over the "
                        "observation period, train/test split dashed, evaluated ID (green) and OOD (red) days.")
    return data
