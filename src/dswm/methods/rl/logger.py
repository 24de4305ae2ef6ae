"""Training curves of the SB3 learners: an SB3 output format (``KVWriter``) collecting the logged scalars.

SB3 writes what its algorithms ``record`` (``train/*``: losses, entropy coefficient, ...; ``rollout/*``: episode
returns) to its output formats at every ``Logger.dump``. :class:`HistoryWriter` keeps the numeric ``train/*`` and
``rollout/*`` values of every dump (all but the counter ``train/n_updates``) since the last
:meth:`HistoryWriter.point`, and ``point(step)`` appends their mean (one value per name) to the history
``{"step": [...], name: [...]}`` that a training manifest carries (the train rule logs it to MLflow). A name
without a value since the last point gets NaN there, so every list is as long as ``step``.
"""
from __future__ import annotations

import math
from collections import defaultdict
from typing import Any

import numpy as np
from stable_baselines3.common.logger import KVWriter, Logger

PREFIXES = ("train/", "rollout/")
"""Names kept in the history."""
SKIP = ("train/n_updates",)
"""Counters, not curves: left out."""


class HistoryWriter(KVWriter):
    """Collects SB3's scalars into one history point per :meth:`point` call."""

    def __init__(self, history: dict[str, list] | None = None):
        self.history: dict[str, list] = {"step": []}
        if history is not None:
            self.history = {k: list(v) for k, v in history.items()}
        self._sums: dict[str, float] = defaultdict(float)
        self._counts: dict[str, int] = defaultdict(int)

    def write(self, key_values: dict[str, Any], key_excluded: dict[str, tuple[str, ...]], step: int = 0) -> None:
        for name, value in key_values.items():
            if not name.startswith(PREFIXES) or name in SKIP or isinstance(value, (bool, str)):
                continue
            if isinstance(value, (int, float, np.number)) or (isinstance(value, np.ndarray) and value.size == 1):
                v = float(value)
                if math.isfinite(v):
                    self._sums[name] += v
                    self._counts[name] += 1

    def point(self, step: int) -> dict[str, float]:
        """Append the mean of every name written since the last point at ``step``; returns that point."""
        row = {k: self._sums[k] / self._counts[k] for k in self._counts}
        self._sums.clear()
        self._counts.clear()
        n = len(self.history["step"])
        for name in row:
            if name not in self.history:
                self.history[name] = [float("nan")] * n
        for name, values in self.history.items():
            if name != "step":
                values.append(row.get(name, float("nan")))
        self.history["step"].append(int(step))
        return row

    def close(self) -> None:
        """Nothing to release."""


def history_logger(writer: HistoryWriter) -> Logger:
    """An SB3 ``Logger`` whose only output is ``writer`` (``model.set_logger``)."""
    return Logger(folder=None, output_formats=[writer])
