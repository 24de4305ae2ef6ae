"""The sections of a dataset's config that the day arithmetic reads (``prep.days``): its train/test split, the
rules that pick its evaluation days and YJMob's week recovery. Below ``prep.config`` (which builds them into each
dataset's section, and re-exports them) and ``prep.days`` (which checks and applies them), so neither imports the
other's module to reach them.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal


@dataclass(frozen=True, kw_only=True)
class Segment:
    """A temporal segment, inclusive on both ends (ISO dates, or day numbers for YJMob)."""

    first: str
    """First day (an ISO date, or a day number for YJMob)."""
    last: str
    """Last day, inclusive."""


@dataclass(frozen=True, kw_only=True)
class Split:
    train: tuple[str, str]
    """[first, last] training days, inclusive."""
    test: tuple[str, str]
    """[first, last] test days, inclusive."""

    def segments(self) -> dict[str, Segment]:
        """Returns {"train": Segment, "test": Segment}."""
        return {"train": Segment(first=self.train[0], last=self.train[1]),
                "test": Segment(first=self.test[0], last=self.test[1])}


@dataclass(frozen=True, kw_only=True)
class EvalRule:
    """How evaluation days are picked from the test segment.

    rule: "test_positions" (values = positions within the test segment), "first_weekdays" (the first
    `count` test days that are not (pseudo-)weekend) or "first_weekend" (the first `count` that are).
    """

    rule: Literal["test_positions", "first_weekdays", "first_weekend"]
    """``test_positions``, ``first_weekdays`` or ``first_weekend`` (see above)."""
    values: tuple[int, ...]
    """Positions in the test segment (``test_positions`` only)."""
    count: int
    """How many days the ``first_*`` rules pick."""


@dataclass(frozen=True, kw_only=True)
class EvalDays:
    id: EvalRule
    """The rule of the in-distribution evaluation days."""
    ood: EvalRule
    """The rule of the out-of-distribution evaluation days."""


@dataclass(frozen=True, kw_only=True)
class WeekRecovery:
    min_lag: int
    """Smallest candidate period, days."""
    max_lag: int
    """Largest candidate period, days."""
    n_weekend_phases: int
    """The lowest-activity phases of the cycle that form the pseudo-weekend."""
