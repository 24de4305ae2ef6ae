"""Day calendars: the tensor's day axis, temporal split, YJMob week recovery and evaluation days.

Tensor day index = position in the list of days: the training segment's days in order, then the test
segment's. Nothing here reads test data to make a decision that affects training: the week period and
pseudo-weekend phases are recovered from TRAINING daily totals only.
"""
from __future__ import annotations

import datetime as dt
from dataclasses import dataclass

import numpy as np

from prep.config import EvalDays, EvalRule, Split, WeekRecovery
from prep.rawio import PrepError


@dataclass(frozen=True, kw_only=True)
class Day:
    """One tensor day. `key` is the date (Milan, Shanghai) or the day number d (YJMob)."""

    index: int
    key: dt.date | int
    split: str  # "train" | "test"

    @property
    def label(self) -> str:
        return self.key.isoformat() if isinstance(self.key, dt.date) else f"d{self.key}"


def _parse_date(text: str, where: str) -> dt.date:
    try:
        return dt.date.fromisoformat(str(text))
    except ValueError as exc:
        raise PrepError(f"config key {where}: expected an ISO date YYYY-MM-DD, found {text!r}") from exc


def _parse_int(text: str, where: str) -> int:
    try:
        return int(text)
    except ValueError as exc:
        raise PrepError(f"config key {where}: expected a day number, found {text!r}") from exc


def calendar_days(split: Split, *, dataset: str) -> list[Day]:
    """All tensor days: training segment then test segment (inclusive ranges of dates).

    Raises:
        PrepError: a segment is empty, reversed, or the test segment does not start after training ends.
    """
    out: list[Day] = []
    bounds = []
    for name, seg in split.segments().items():
        a = _parse_date(seg.first, f"datasets.{dataset}.split.{name}[0]")
        b = _parse_date(seg.last, f"datasets.{dataset}.split.{name}[1]")
        if b < a:
            raise PrepError(f"config key datasets.{dataset}.split.{name}: last day {b} is before first day {a}")
        bounds.append((a, b))
        for k in range((b - a).days + 1):
            out.append(Day(index=len(out), key=a + dt.timedelta(days=k), split=name))
    if bounds[1][0] <= bounds[0][1]:
        raise PrepError(f"config key datasets.{dataset}.split: test segment must start after the training "
                        f"segment ends (temporal split); found train {bounds[0]}, test {bounds[1]}")
    return out


def numbered_days(split: Split, *, dataset: str, n_days: int) -> list[Day]:
    """Tensor days for a dataset with numbered days (YJMob d = 0..n_days-1)."""
    out: list[Day] = []
    prev_last = -1
    for name, seg in split.segments().items():
        a = _parse_int(seg.first, f"datasets.{dataset}.split.{name}[0]")
        b = _parse_int(seg.last, f"datasets.{dataset}.split.{name}[1]")
        if not (0 <= a <= b < n_days) or a <= prev_last:
            raise PrepError(f"config key datasets.{dataset}.split.{name}: expected {prev_last + 1} <= first <= "
                            f"last <= {n_days - 1}, found [{a}, {b}]")
        prev_last = b
        base = len(out)
        out.extend([Day(index=base + k, key=a + k, split=name) for k in range(b - a + 1)])
    return out


@dataclass(frozen=True, kw_only=True)
class Week:
    """Recovered week structure (YJMob)."""

    lag: int  # period with the highest autocorrelation of training daily totals
    acf: dict[int, float]  # autocorrelation per candidate lag
    phase_means: list[float]  # mean training daily total per phase (d mod lag)
    pseudo_weekend_phases: list[int]  # the lowest-activity phases


def autocorrelation(x: np.ndarray, lag: int) -> float:
    """Sample autocorrelation of a series at `lag` (biased estimator, normalized by the lag-0 sum)."""
    y = np.asarray(x, dtype=np.float64) - float(np.mean(x))
    den = float(np.dot(y, y))
    if den == 0.0 or lag >= len(y):
        return 0.0
    return float(np.dot(y[:-lag], y[lag:]) / den)


def recover_week(day_numbers: np.ndarray, totals: np.ndarray, cfg: WeekRecovery) -> Week:
    """Recovers the week period and pseudo-weekend phases from TRAINING daily totals.

    Args:
        day_numbers: (n,) int day numbers d of the training days (consecutive).
        totals: (n,) daily demand totals of those days.
        cfg: candidate lag range and number of pseudo-weekend phases.
    Returns:
        Week with the peak lag and the `n_weekend_phases` phases (d mod lag) of lowest mean total.
    """
    hi = min(cfg.max_lag, len(totals) // 2)
    if hi < cfg.min_lag:
        raise PrepError(f"week recovery needs at least {2 * cfg.min_lag} training days, found {len(totals)}")
    acf = {k: autocorrelation(totals, k) for k in range(cfg.min_lag, hi + 1)}
    lag = max(acf, key=lambda k: (acf[k], -k))
    phases = np.asarray(day_numbers) % lag
    means = [float(np.mean(totals[phases == p])) for p in range(lag)]
    weekend = sorted(int(p) for p in np.argsort(means, kind="stable")[: cfg.n_weekend_phases])
    return Week(lag=lag, acf=acf, phase_means=means, pseudo_weekend_phases=weekend)


def pick_eval_days(days: list[Day], weekend: list[bool], rules: EvalDays, *, dataset: str) -> dict[str, list[int]]:
    """Evaluation days as tensor day indices.

    Args:
        days: tensor days.
        weekend: per tensor day, (pseudo-)weekend flag.
        rules: the dataset's eval-day rules.
    Returns:
        {"id": [...], "ood": [...]} tensor day indices, each list sorted.
    Raises:
        PrepError: the test segment has too few matching days, or a position is out of range.
    """
    test = [d for d in days if d.split == "test"]
    out: dict[str, list[int]] = {}
    for name in ("id", "ood"):
        rule: EvalRule = getattr(rules, name)
        where = f"datasets.{dataset}.eval_days.{name}"
        if rule.rule == "test_positions":
            bad = [v for v in rule.values if not 0 <= v < len(test)]
            if bad or not rule.values:
                raise PrepError(f"config key {where}.values: expected positions in 0..{len(test) - 1}, found "
                                f"{list(rule.values)}")
            picked = [test[v].index for v in rule.values]
        else:
            want = rule.rule == "first_weekend"
            cands = [d.index for d in test if weekend[d.index] == want]
            if rule.count < 1 or len(cands) < rule.count:
                raise PrepError(f"config key {where}: rule {rule.rule} needs {rule.count} days, the test segment "
                                f"has {len(cands)}")
            picked = cands[: rule.count]
        out[name] = sorted(picked)
    if set(out["id"]) & set(out["ood"]):
        raise PrepError(f"config key datasets.{dataset}.eval_days: id and ood days overlap: "
                        f"{sorted(set(out['id']) & set(out['ood']))}")
    return out
