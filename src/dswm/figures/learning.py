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
                 ("charts/episode_reward", "training return"), ("losses/dem", "world-model demand loss"))
"""The history column drawn beside a learner's curve, the first one its history has, and its axis label (DSWM's
world model has no return: its demand reconstruction loss; its total loss is no measure of learning, its KL terms
rise as the posterior comes to use the latent: 3.9 -> 6.1 on the demo's curve while the demand loss fell 2.7x)."""
FALLING = frozenset({"losses/dem"})
"""Series that fall when the learner learns (a loss); the others rise (a return)."""
SEEDED = frozenset({"charts/episode_reward"})
"""Series whose first value is not the learner's own: TD-MPC's episode reward starts as the mean reward of its
pre-collected (heuristic) transitions and is repeated until its first own episode."""
MARGIN = 0.05
"""Criterion (b) of a learner that has learned: its validation served ratio at least this much above its untrained
policy's, or, where the untrained policy already serves within this much of Static, not below it."""
VERDICT_COLUMNS = ("method", "seed", "series", "units", "first_tenth", "last_tenth", "rise", "rise_se",
                   "return_rises", "untrained_sr", "final_sr", "static_sr", "untrained_near_static", "sr_gain",
                   "sr_learned", "learned", "learned_at_fraction", "learned_at_transitions",
                   "learned_at_gradient_steps", "cap_transitions", "cap_gradient_steps")
"""learning_verdict.csv: one row per learner, criterion (a) on its whole run and (b) at its cap, and the smallest
snapshot at which both hold on the history up to it (null: none)."""
CSV_COLUMNS = ("method", "seed", "fraction", "transitions", "gradient_steps", "probe_sr", "untrained", "static_sr",
               "greedy_sr", "days", "dataset")
CAPTION = ("Learning curves: served ratio on the validation days {days} ({dataset}; the last training days, held out "
           "of every learning run, never a test day) of one run per learner (seed {seeds}) at its cap, its "
           "snapshots at fractions {ladder} of the cap and the untrained model (hollow marker; at a quarter of the "
           "first snapshot's x where it consumed none), against the environment transitions consumed (log scale; "
           "pre-collected ones included; against the gradient steps where snapshots share their transitions); "
           "{refs} on the same days as horizontal lines. Right: the run's training return (DSWM: its world-model "
           "demand loss) from its loss history; the title says where the learner learned (learning_verdict.csv). "
           "Diagnostic only: never in a table.")



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


def training_units(history: pl.DataFrame, name: str) -> pl.DataFrame:
    """The learner's own training series ``name`` as (step, value), one row per logged unit (round or episode):
    nulls and NaNs dropped, a value repeated from the row before dropped (a series logged again between its
    rounds), and for a :data:`SEEDED` series its first value (not the learner's own)."""
    rows = (history.select("step", name).drop_nulls().filter(pl.col(name).is_not_nan()).sort("step")
            .filter(pl.col(name) != pl.col(name).shift(1).fill_null(float("nan"))))
    return rows.slice(1) if name in SEEDED else rows


def return_rise(values, *, falling: bool = False) -> tuple[float, float, float, float]:
    """Criterion (a) of the learning-curves issue on one series: (first tenth's mean, last tenth's mean, the rise
    from the first to the last, the rise's standard error); a tenth is at least one unit. ``falling``: a loss, whose
    rise is its fall. With fewer than two units per tenth the standard error is infinite (no verdict can pass)."""
    import numpy as np

    v = np.asarray(values, dtype=np.float64)
    if v.size < 2:
        return float("nan"), float("nan"), float("nan"), float("inf")
    k = max(1, v.size // 10)
    first, last = v[:k], v[-k:]
    rise = (first.mean() - last.mean()) if falling else (last.mean() - first.mean())
    se = (float(np.sqrt(first.var(ddof=1) / k + last.var(ddof=1) / k)) if k >= 2 else float("inf"))
    return float(first.mean()), float(last.mean()), float(rise), se


def sr_learned(untrained: float, sr: float, static: float | None) -> bool:
    """Criterion (b): ``sr`` at least :data:`MARGIN` above ``untrained``, or not below it where the untrained
    policy serves within :data:`MARGIN` of Static (an initial policy that already holds the fleet still)."""
    if static is not None and abs(untrained - static) <= MARGIN:
        return sr >= untrained
    return sr >= untrained + MARGIN


def learning_verdict(table: pl.DataFrame, histories: pl.DataFrame) -> pl.DataFrame:
    """Whether each learner learned (:data:`VERDICT_COLUMNS`): (a) its training series (:func:`return_series`)
    rises from the first tenth of its units to the last by more than twice the standard error, and (b)
    :func:`sr_learned` at its cap; ``learned_at_*``: the first snapshot at which (a), on the units logged up to
    its fraction of the run (of the history's last step: every fit logs a point at its end), and (b), at its
    served ratio, both hold.
    """
    rows = []
    for (method, seed), g in table.group_by(["method", "seed"], maintain_order=True):
        g = g.sort("fraction")
        untrained = g.filter(pl.col("untrained"))
        trained = g.filter(~pl.col("untrained"))
        if untrained.is_empty() or trained.is_empty():
            continue
        static = g["static_sr"].drop_nulls()
        static = float(static[0]) if static.len() else None
        u_sr, cap = float(untrained["probe_sr"][0]), trained.row(-1, named=True)
        history = histories.filter((pl.col("method") == method) & (pl.col("seed") == seed))
        series = return_series(history)
        row = {"method": method, "seed": seed, "untrained_sr": u_sr, "final_sr": cap["probe_sr"],
               "static_sr": static, "untrained_near_static": static is not None and abs(u_sr - static) <= MARGIN,
               "sr_gain": cap["probe_sr"] - u_sr, "sr_learned": sr_learned(u_sr, cap["probe_sr"], static),
               "cap_transitions": cap["transitions"], "cap_gradient_steps": cap["gradient_steps"]}
        units = training_units(history, series[0]) if series else None
        if series is None or units.is_empty():
            rows.append({**row, "series": None, "units": 0, "return_rises": False, "learned": False})
            continue
        name, falling = series[0], series[0] in FALLING
        end = float(history["step"].max())
        first, last, rise, se = return_rise(units[name].to_numpy(), falling=falling)
        row.update(series=name, units=units.height, first_tenth=first, last_tenth=last, rise=rise, rise_se=se,
                   return_rises=bool(rise > 2 * se))
        row["learned"] = row["return_rises"] and row["sr_learned"]
        for snap in trained.iter_rows(named=True):
            upto = units.filter(pl.col("step") <= snap["fraction"] * end + 1e-9)[name].to_numpy()
            _, _, r, e = return_rise(upto, falling=falling)
            if r > 2 * e and sr_learned(u_sr, snap["probe_sr"], static):
                row.update(learned_at_fraction=snap["fraction"], learned_at_transitions=snap["transitions"],
                           learned_at_gradient_steps=snap["gradient_steps"])
                break
        rows.append(row)
    schema = {c: pl.Float64 for c in VERDICT_COLUMNS}
    schema.update(method=pl.String, seed=pl.Int64, series=pl.String, units=pl.Int64, return_rises=pl.Boolean,
                  untrained_near_static=pl.Boolean, sr_learned=pl.Boolean, learned=pl.Boolean,
                  learned_at_transitions=pl.Int64, learned_at_gradient_steps=pl.Int64, cap_transitions=pl.Int64,
                  cap_gradient_steps=pl.Int64)
    return pl.DataFrame([{c: r.get(c) for c in VERDICT_COLUMNS} for r in rows], schema=schema, orient="row")


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
                         out: Mapping[str, str | Path], verdict: pl.DataFrame | None = None) -> pl.DataFrame:
    """Draw the learning curves and write them (PNG, PDF and the CSV :func:`curve_table` gave).

    Args:
        table: :func:`curve_table`.
        histories: the learning runs' loss histories (``dswm.pipeline.history.read_histories``).
        order: the learners, top to bottom; labels: {method: label}; ladder: the fractions of the cap.
        out: {"png", "pdf", "csv"} paths.
        verdict: :func:`learning_verdict`; each panel's title then says where its learner learned.
    """
    order = [m for m in order if m in set(table["method"].to_list())]
    fig, axes = plt.subplots(max(1, len(order)), 2, figsize=(11.0, 2.7 * max(1, len(order))), squeeze=False,
                             gridspec_kw={"width_ratios": [1.4, 1.0]})
    for (ax, ax_ret), method in zip(axes, order):
        rows = table.filter(pl.col("method") == method).sort("fraction")
        _draw_curve(ax, rows, labels.get(method, method) + _verdict_note(verdict, method))
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


def _verdict_note(verdict: pl.DataFrame | None, method: str) -> str:
    """' - learned at F of the cap (N transitions, M gradient steps)', ' - not learned at its cap', or '' (no
    verdict)."""
    if verdict is None:
        return ""
    rows = verdict.filter(pl.col("method") == method)
    if rows.is_empty():
        return ""
    r = rows.row(0, named=True)
    if r["learned_at_fraction"] is None:
        return " - not learned at its cap"
    return (f" - learned at {r['learned_at_fraction']:g} of the cap ({r['learned_at_transitions']:,} transitions, "
            f"{r['learned_at_gradient_steps']:,} gradient steps)")


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
