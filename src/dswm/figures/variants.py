"""The per-day rows of the extra runs (results/extra/<dataset>/<variant>/<method>/seed<seed>/days.parquet) beside
the main evaluations they vary: the reference point of a sweep (s = 1, the scenario's own K, u x 1) is the main
evaluation's days.parquet cut to the days the extra runs evaluate (``figures.eval_days``: the first N days of
each split, in the order the main file holds them)."""
from __future__ import annotations

from typing import Mapping, Sequence

import polars as pl

from dswm.settings import EvalDayLimits, parse_variant


def first_days(days: pl.DataFrame, limits: EvalDayLimits) -> pl.DataFrame:
    """Per (method, seed, split): the first ``limits.<split>`` rows of ``days`` in file order (None: every row,
    0: none), i.e. the days an extra run with these limits evaluates.

    Raises:
        ValueError: a (method, seed) holds fewer days of a split than ``limits`` asks (the main evaluation ran
            fewer days than the extra runs, so no reference on the same days exists).
    """
    parts = []
    for split in ("id", "ood"):
        n = getattr(limits, split)
        part = days.filter(pl.col("split") == split).with_columns(
            pl.int_range(pl.len()).over(["method", "seed"]).alias("_rank"))
        if n is not None:
            short = part.group_by(["method", "seed"]).agg(pl.len().alias("n")).filter((pl.col("n") < n) & (n > 0))
            if short.height:
                row = short.row(0, named=True)
                raise ValueError(f"main result of {row['method']} seed {row['seed']}: {row['n']} {split} day(s); "
                                 f"figures.eval_days.{split} asks {n} (the main evaluation must cover the days "
                                 f"of the extra runs: raise profiles.<profile>.eval_days.{split})")
            part = part.filter(pl.col("_rank") < n)
        parts.append(part.drop("_rank"))
    return pl.concat(parts, how="diagonal_relaxed")


RUN_SCHEMA = {"method": pl.String, "seed": pl.Int32, "split": pl.String, "day": pl.Int32, "sr_mean": pl.Float64,
              "variant": pl.String, "kind": pl.String, "value": pl.Float64}
"""The columns of :func:`with_variant` that the figures read (an empty frame of them stands for no extra run)."""


def with_variant(days: pl.DataFrame | None) -> pl.DataFrame:
    """``days`` of extra runs (their ``variant`` column, e.g. "K8") with columns ``kind`` ("do", "K" or "u") and
    ``value`` (s, K or the factor of u, Float64); None or an empty frame: no rows, the columns of
    :data:`RUN_SCHEMA`."""
    if days is None or not days.height:
        return pl.DataFrame(schema=RUN_SCHEMA)
    parsed = {name: parse_variant(name) for name in days["variant"].unique().to_list()}
    return days.with_columns(pl.col("variant").replace_strict({n: v.kind for n, v in parsed.items()}).alias("kind"),
                             pl.col("variant").replace_strict({n: float(v.value) for n, v in parsed.items()},
                                                              return_dtype=pl.Float64).alias("value"))


def check_same_days(reference: pl.DataFrame, runs: pl.DataFrame, what: str) -> None:
    """Raise ValueError naming ``what`` when the reference rows and the extra runs' rows cover different
    (split, day) pairs (they must be compared on the same days)."""
    ref = set(reference.select("split", "day").iter_rows())
    run = set(runs.select("split", "day").iter_rows())
    if ref != run:
        raise ValueError(f"{what}: the reference (main evaluation) covers days {sorted(ref)}, the extra runs "
                         f"{sorted(run)}; expected the same days (figures.eval_days cuts both)")


def reference_rows(main: pl.DataFrame, runs: pl.DataFrame, *, methods, seeds, limits: EvalDayLimits, kind: str,
                   value: float, what: str) -> pl.DataFrame:
    """The reference point of a sweep: ``main``'s rows of ``methods`` and ``seeds`` on the days of ``limits``,
    with ``kind`` and ``value`` columns; checked to cover the days of ``runs`` (when there are any)."""
    ref = main.filter(pl.col("method").is_in(list(methods)) & pl.col("seed").is_in(list(seeds)))
    missing = sorted({(m, s) for m in methods for s in seeds} - set(ref.select("method", "seed").iter_rows()))
    if missing:
        raise ValueError(f"{what}: no main result of (method, seed) {missing}; expected the main evaluations of "
                         f"figures.dataset for every seed of figures.seeds")
    ref = first_days(ref, limits).with_columns(pl.lit(kind).alias("kind"), pl.lit(float(value)).alias("value"))
    if runs.height:
        check_same_days(ref, runs, what)
    return ref


def line_label(label: str, split: str, splits: Sequence[str], split_labels: Mapping[str, str]) -> str:
    """A line's legend entry: the method's ``label``, with the split's when the panel draws more than one split."""
    return label if len(splits) == 1 else f"{label}, {split_labels[split]}"
