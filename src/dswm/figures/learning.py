"""The learning curves (results/figures/learning_curves.{png,pdf,csv}; workflow/rules/learning.smk): per learner,
the served ratio of its one run's snapshots on the validation days against the environment transitions consumed
(log scale; the untrained model first), with the reference methods (Static, Greedy) on the same days as horizontal
lines, and beside it the run's training return from its loss history.

The CSV has one row per (learner, snapshot): ``method``, ``seed``, ``fraction`` (0: untrained), ``transitions``,
``gradient_steps``, ``probe_sr`` (the mean served ratio over the validation days), ``untrained``, ``static_sr`` and
``greedy_sr`` (the references' means on the same days; null for a reference ``methods.run`` lacks), ``days`` (the
validation days' labels, ";"-joined) and ``dataset``.
"""
from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence

import polars as pl

from matplotlib.ticker import NullFormatter

from dswm.figures.common import plt, save_figure

RETURN_SERIES = (("rollout/ep_rew_mean", "training return"), ("charts/episode_return", "training return"),
                 ("charts/episode_reward", "training return"), ("losses/loss", "world-model loss"))
"""The history column drawn beside a learner's curve, the first one its history has, and its axis label (DSWM's
world model has no return: its loss)."""
CSV_COLUMNS = ("method", "seed", "fraction", "transitions", "gradient_steps", "probe_sr", "untrained", "static_sr",
               "greedy_sr", "days", "dataset")
CAPTION = ("Learning curves: served ratio on the validation days {days} ({dataset}; the last training days, held out "
           "of every learning run, never a test day) of one run per learner (seed {seeds}) at its cap, its "
           "snapshots at fractions {ladder} of the cap and the untrained model (hollow marker; at a quarter of the "
           "first snapshot's x where it consumed none), against the environment transitions consumed (log scale; "
           "pre-collected ones included; against the gradient steps where snapshots share their transitions); "
           "{refs} on the same days as horizontal lines. Right: the run's training return (DSWM: its world-model "
           "loss) from its loss history. Diagnostic only: never in a table.")



def curve_table(scores: pl.DataFrame, references: pl.DataFrame) -> pl.DataFrame:
    """One row per (learner, snapshot) with the references' values on the same days (:data:`CSV_COLUMNS`).

    Args:
        scores: the learners' score rows (one per snapshot and validation day).
        references: the reference methods' score rows (one per validation day).
    Raises:
        ValueError: a learner or reference scored on other days than the rest (the message names it).
    """
    days = _days(scores, references)
    refs = {m: float(g["sr_mean"].mean()) for (m,), g in references.group_by(["method"], maintain_order=True)}
    table = (scores.group_by(["method", "seed", "fraction"], maintain_order=True)
             .agg(pl.col("n_transitions").first().alias("transitions"), pl.col("gradient_steps").first(),
                  pl.col("sr_mean").mean().alias("probe_sr"), pl.col("untrained").first(),
                  pl.col("dataset").first())
             .sort(["method", "fraction"], maintain_order=True))
    return table.with_columns(pl.lit(refs.get("static"), dtype=pl.Float64).alias("static_sr"),
                              pl.lit(refs.get("greedy"), dtype=pl.Float64).alias("greedy_sr"),
                              pl.lit(";".join(days)).alias("days")).select(CSV_COLUMNS)


def _days(scores: pl.DataFrame, references: pl.DataFrame) -> list[str]:
    """The validation days' labels every snapshot and reference was scored on, in day order."""
    both = pl.concat([scores.select("method", "fraction", "day", "label"),
                      references.select("method", "day", "label").with_columns(pl.lit(None, pl.Float64)
                                                                               .alias("fraction"))
                      .select("method", "fraction", "day", "label")])
    want = None
    for (method, fraction), g in both.group_by(["method", "fraction"], maintain_order=True):
        got = g.sort("day")["label"].to_list()
        if want is None:
            want = got
        elif got != want:
            raise ValueError(f"learning curves: {method} (fraction {fraction}) was scored on {got}, the others on "
                             f"{want}; re-run its learning_score job")
    return want or []


def return_series(history: pl.DataFrame) -> tuple[str, str] | None:
    """(column, axis label) of the series drawn beside a learner's curve (:data:`RETURN_SERIES`), or None."""
    for name, label in RETURN_SERIES:
        if name in history.columns and history[name].drop_nulls().len():
            return name, label
    return None


def draw_learning_curves(table: pl.DataFrame, histories: pl.DataFrame, *, order: Sequence[str],
                         labels: Mapping[str, str], ladder: Sequence[float], profile: str, source: str,
                         out: Mapping[str, str | Path]) -> pl.DataFrame:
    """Draw the learning curves and write them (PNG, PDF and the CSV :func:`curve_table` gave).

    Args:
        table: :func:`curve_table`.
        histories: the learning runs' loss histories (``dswm.pipeline.history.read_histories``).
        order: the learners, top to bottom; labels: {method: label}; ladder: the fractions of the cap.
        out: {"png", "pdf", "csv"} paths.
    """
    order = [m for m in order if m in set(table["method"].to_list())]
    fig, axes = plt.subplots(max(1, len(order)), 2, figsize=(11.0, 2.7 * max(1, len(order))), squeeze=False,
                             gridspec_kw={"width_ratios": [1.4, 1.0]})
    for (ax, ax_ret), method in zip(axes, order):
        rows = table.filter(pl.col("method") == method).sort("fraction")
        _draw_curve(ax, rows, labels.get(method, method))
        _draw_return(ax_ret, histories.filter(pl.col("method") == method))
    if not order:
        axes[0][0].text(0.5, 0.5, "no learner in this profile", ha="center", va="center",
                        transform=axes[0][0].transAxes)
    fig.tight_layout(rect=(0, 0.03, 1, 0.98))
    days = table["days"][0] if table.height else "-"
    refs = " and ".join(n for n, c in (("Static", "static_sr"), ("Greedy", "greedy_sr"))
                        if table.height and table[c].drop_nulls().len()) or "no reference"
    save_figure(fig, table, png=out["png"], pdf=out["pdf"], csv=out["csv"], profile=profile, source=source,
                caption=CAPTION.format(days=days.replace(";", ", "), dataset=", ".join(sorted(set(
                    table["dataset"].to_list()))) or "-", seeds=", ".join(map(str, sorted(set(
                        table["seed"].to_list())))) or "-", ladder=", ".join(f"{f:g}" for f in ladder), refs=refs))
    return table


def _draw_curve(ax, rows: pl.DataFrame, title: str) -> None:
    """One learner's served ratio against transitions; the untrained point left of the smallest positive x."""
    trained = rows.filter(~pl.col("untrained"))
    x_col, x_label = curve_axis(rows)
    x, y = trained[x_col].to_numpy(), trained["probe_sr"].to_numpy()
    positive = x[x > 0]
    left = float(positive.min()) / 4 if positive.size else 1.0
    ax.plot(x, y, "o-", ms=4, color="C0", label="snapshots")
    for r in rows.filter(pl.col("untrained")).iter_rows(named=True):
        ux = r[x_col] if r[x_col] > 0 else left
        ax.plot([ux], [r["probe_sr"]], "o", mfc="none", color="C0", ms=6, label="untrained")
        if len(x):
            ax.plot([ux, x[0]], [r["probe_sr"], y[0]], ":", color="C0", lw=1)
    for col, name, style in (("static_sr", "Static", "--"), ("greedy_sr", "Greedy", "-.")):
        value = rows[col].drop_nulls()
        if value.len():
            ax.axhline(float(value[0]), ls=style, color="0.4", lw=1, label=name)
    ax.set_xscale("log")
    ax.xaxis.set_minor_formatter(NullFormatter())  # labelled decades only: minor labels overlap on short ranges
    ax.set_xlabel(x_label)
    ax.set_ylabel("validation served ratio")
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7, loc="best")


def curve_axis(rows: pl.DataFrame) -> tuple[str, str]:
    """(column, label) of a learner's x axis: the environment transitions when they grow from each snapshot of the
    ladder to the next, else (snapshots taken on the same pre-collected transitions, as DSWM's world model and
    TD-MPC's seed phase) its gradient steps."""
    trained = rows.filter(~pl.col("untrained")).sort("fraction")
    transitions = trained["transitions"].to_list()
    if rows["gradient_steps"].null_count() or all(b > a for a, b in zip(transitions, transitions[1:])):
        return "transitions", "environment transitions (log scale)"
    low, high = min(transitions), max(transitions)
    span = (f"all {low:,} transitions pre-collected" if low == high
            else f"{low:,}-{high:,} transitions, pre-collected ones included")
    return "gradient_steps", f"gradient steps (log scale; {span})"


def _draw_return(ax, history: pl.DataFrame) -> None:
    """One learner's training return (or loss) against its history's step."""
    series = return_series(history)
    if series is None:
        ax.text(0.5, 0.5, "no training return logged", ha="center", va="center", transform=ax.transAxes)
        return
    name, label = series
    rows = history.select("step", name).drop_nulls().sort("step")
    ax.plot(rows["step"].to_numpy(), rows[name].to_numpy(), "-", color="C1", lw=1.2)
    ax.set_xlabel("training step (history)")
    ax.set_ylabel(label)
    ax.grid(alpha=0.3)
