"""The learning curves' protocol (workflow/rules/learning.smk): which days a learner trains on and which score it.

As ``select`` does (``dswm.protocol.selection``), the TRAINING days of the dataset are split in time order: the last
``validation_days`` are held out of every learning run and score its snapshots, the earlier ones train it. Test days
are never read. The scores are diagnostic: they are written under :data:`LEARNING_DIR`, never beside a table's
source, and every row carries ``split`` = :data:`VALIDATION_SPLIT` (a table's rows are "id" or "ood").
"""
from __future__ import annotations

from typing import Sequence

LEARNING_DIR = "results/learning"
"""Where every learning run and score file lives (outside ``results/<dataset>/``, the tables' sources)."""
SCORE_FILE = "curve.parquet"
"""The scores of one method: ``LEARNING_DIR/<dataset>/<method>/seed<seed>/curve.parquet``."""
VALIDATION_SPLIT = "validation"
"""The ``split`` of every score row."""


def learning_days(tensor, validation_days: int) -> tuple[list[int], list[int]]:
    """(training days, validation days) of a learning run: the tensor's training days in time order, all but the
    last ``validation_days``, and those last ones.

    Raises:
        ValueError: fewer than ``validation_days + 1`` training days, or a validation day that is no training day
            or is a test or evaluation day (the message names the day).
    """
    train = [int(d) for d in tensor.train_days]
    n = int(validation_days)
    if n < 1 or len(train) <= n:
        raise ValueError(f"meta.json of {tensor.meta['dataset']}: {len(train)} training day(s), but "
                         f"learning.validation_days = {validation_days} needs at least {n + 1} (at least one trains)")
    fit, val = train[:-n], train[-n:]
    check_validation_days(tensor, val)
    return fit, val


def check_validation_days(tensor, days: Sequence[int]) -> None:
    """Every day of ``days`` is a training day and none a test or evaluation day.

    Raises:
        ValueError: naming the day's label and its split.
    """
    train = {int(d) for d in tensor.train_days}
    held = {int(d) for d in tensor.test_days} | {int(d) for s in ("id", "ood") for d in tensor.eval_days(s)}
    for d in days:
        if int(d) not in train or int(d) in held:
            raise ValueError(f"meta.json of {tensor.meta['dataset']}: day {tensor.labels[int(d)]} (index {d}) is "
                             f"not a training day; the learning curves score training days only, never a test day")


def score_path(dataset: str, method: str, seed: int) -> str:
    """The score file of one learner or reference, relative to the workflow's root."""
    return f"{LEARNING_DIR}/{dataset}/{method}/seed{seed}/{SCORE_FILE}"
