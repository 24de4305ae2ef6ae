"""The loss history of a train job as a result file (``results/<dataset>/<method>/seed<seed>/train_history.parquet``).

A train job logs its method's loss history to MLflow and writes the same numbers here, because figures are drawn
from result files only. Wide format: one row per logged step, columns ``dataset``, ``method``, ``seed``, ``step``
(the gradient or update step the row ends, Int64) and one Float64 column per series, named as in MLflow (DSWM:
``losses/loss``, ``losses/dem``, ...; see ``dswm.methods.dswm.training.HISTORY_KEYS``). A method without a history
writes the identity columns and ``step`` with no row.
"""
from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence

import polars as pl

from prep.atomic import atomic_path

IDENTITY_COLUMNS = ("dataset", "method", "seed", "step")


def history_frame(history: Mapping[str, Sequence[float]], steps: Sequence[int] | None, *, dataset: str, method: str,
                  seed: int) -> pl.DataFrame:
    """The history as a wide frame (see the module docstring).

    Args:
        history: {series name: values}, every series as long as ``steps``.
        steps: the step of each value; None: 0, 1, ... (as MLflow logs a series without steps).

    Raises:
        ValueError: a series' length differs from the steps', or a series is named like an identity column.
    """
    n = len(steps) if steps is not None else max((len(v) for v in history.values()), default=0)
    steps = list(range(n)) if steps is None else [int(s) for s in steps]
    for name, values in history.items():
        if name in IDENTITY_COLUMNS:
            raise ValueError(f"loss history of {dataset}/{method}/seed{seed}: series {name!r} has the name of an "
                             f"identity column {IDENTITY_COLUMNS}")
        if len(values) != n:
            raise ValueError(f"loss history of {dataset}/{method}/seed{seed}: series {name!r} has {len(values)} "
                             f"values, expected {n} (one per logged step)")
    return pl.DataFrame({"dataset": [dataset] * n, "method": [method] * n, "seed": [int(seed)] * n, "step": steps,
                         **{name: [float(v) for v in values] for name, values in history.items()}},
                        schema={"dataset": pl.String, "method": pl.String, "seed": pl.Int32, "step": pl.Int64,
                                **{name: pl.Float64 for name in history}})


def write_history(path: str | Path, history: Mapping[str, Sequence[float]], steps: Sequence[int] | None, *,
                  dataset: str, method: str, seed: int) -> pl.DataFrame:
    """Write :func:`history_frame` to ``path`` atomically (temp file, then rename); returns the frame written."""
    frame = history_frame(history, steps, dataset=dataset, method=method, seed=seed)
    with atomic_path(path) as tmp:
        frame.write_parquet(tmp)
    return frame


def read_histories(paths: Sequence[str | Path]) -> pl.DataFrame:
    """The history files ``paths`` as one frame (series a file lacks are null), in the order given.

    Raises:
        ValueError: no path given, or a file lacks an identity column.
    """
    if not paths:
        raise ValueError("no train_history.parquet given: expected at least one")
    frames = []
    for p in paths:
        frame = pl.read_parquet(p)
        missing = [c for c in IDENTITY_COLUMNS if c not in frame.columns]
        if missing:
            raise ValueError(f"{p}: not a training history (missing column(s) {missing}; expected "
                             f"{list(IDENTITY_COLUMNS)} and one column per series)")
        frames.append(frame)
    return pl.concat(frames, how="diagonal_relaxed")
