"""What every figure shares: pyplot (on the package's Agg backend), the corner note, and the atomic PNG + PDF +
CSV writer."""
from __future__ import annotations

from pathlib import Path
from typing import Iterable, Mapping, Sequence

import matplotlib.pyplot as plt  # the Agg backend is set by the package (dswm/figures/__init__.py)
import polars as pl

from prep.atomic import atomic_path

DPI = 150
"""Raster resolution of the PNG files (the PDF is vector)."""


def outputs(stem: str | Path) -> dict[str, Path]:
    """{"png", "pdf", "csv"} paths of the figure ``stem`` (a path without suffix, e.g. results/figures/main)."""
    stem = Path(stem)
    return {ext: stem.with_name(stem.name + "." + ext) for ext in ("png", "pdf", "csv")}


def corner_note(fig, *, profile: str, source: str | Mapping[str, str]) -> None:
    """Write "profile: P · data: S" in the figure's upper right corner.

    Args:
        source: the data source (``meta["source"]``: demo or raw), or {dataset: source}.
    """
    if isinstance(source, Mapping):
        source = ", ".join(f"{d}: {s}" for d, s in source.items())
    fig.text(0.995, 0.995, f"profile: {profile} · data: {source}", ha="right", va="top", fontsize=7,
             color="0.35")


def save_figure(fig, data: pl.DataFrame, *, png: str | Path, pdf: str | Path, csv: str | Path, profile: str,
                source: str | Mapping[str, str], caption: str) -> None:
    """Write ``fig`` as PNG and PDF and ``data`` (the numbers it draws) as CSV, each atomically, then close it.

    Args:
        caption: the figure's caption, naming the paper's figure it reproduces ("Paper Fig. 3: ..."); drawn as
            the figure's suptitle footer and written as the CSV's first comment line.
        profile, source: see :func:`corner_note`.
    """
    corner_note(fig, profile=profile, source=source)
    fig.text(0.005, 0.005, caption, ha="left", va="bottom", fontsize=7, wrap=True)
    # bbox_inches="tight": the saved image grows to hold legends placed outside the axes
    with atomic_path(png) as tmp:
        fig.savefig(tmp, dpi=DPI, format="png", bbox_inches="tight")
    with atomic_path(pdf) as tmp:
        fig.savefig(tmp, format="pdf", bbox_inches="tight")
    plt.close(fig)
    with atomic_path(csv) as tmp, open(tmp, "w", encoding="utf-8") as fh:
        fh.write(f"# {caption} (profile: {profile})\n")
        data.write_csv(fh)


def read_csv(path: str | Path) -> pl.DataFrame:
    """A CSV written by :func:`save_figure` back (its caption comment line skipped)."""
    return pl.read_csv(path, comment_prefix="#")


def read_parquets(paths: Iterable[str | Path]) -> pl.DataFrame:
    """Parquet files ``paths`` (probe or learning-curve score files) as one frame, columns united; an empty frame with
    no columns when there are none."""
    frames = [pl.read_parquet(p) for p in paths]
    return pl.concat(frames, how="diagonal_relaxed") if frames else pl.DataFrame()


def read_days(paths: Iterable[str | Path]) -> pl.DataFrame:
    """The per-day result files ``paths`` (days.parquet) as one frame, in the order given."""
    frames = [pl.read_parquet(p) for p in paths]
    if not frames:
        raise ValueError("no result files given: expected at least one days.parquet")
    return pl.concat(frames, how="diagonal_relaxed")


def mean_std(df: pl.DataFrame, by: Sequence[str], value: str) -> pl.DataFrame:
    """Per ``by`` group: the mean over seeds of each seed's mean of ``value``, its sample std over seeds (ddof=1,
    as in the tables; 0 for one seed) and the number of seeds, as columns ``<value>``, ``<value>_std`` and
    ``seeds``."""
    per_seed = df.group_by([*by, "seed"], maintain_order=True).agg(pl.col(value).mean())
    return per_seed.group_by(list(by), maintain_order=True).agg(
        pl.col(value).mean().alias(value), pl.col(value).std(ddof=1).fill_null(0.0).alias(value + "_std"),
        pl.len().alias("seeds"))
