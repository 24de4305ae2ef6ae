"""Day calendars: the tensor's day axis, temporal split, YJMob week recovery and evaluation days.

Tensor day index = position in the list of days: the training segment's days in order, then the test
segment's. Nothing here reads test data to make a decision that affects training: the week period and
pseudo-weekend phases are recovered from TRAINING daily totals only.
"""
from __future__ import annotations

import datetime as dt
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from prep.typed import ConfigError
from prep.sections import EvalDays, EvalRule, Split, WeekRecovery
from prep.rawio import PrepError, describe_files


@dataclass(frozen=True, kw_only=True)
class Day:
    """One tensor day. `key` is the date (Milan, Shanghai) or the day number d (YJMob)."""

    index: int
    key: dt.date | int
    split: str  # "train" | "test"

    @property
    def label(self) -> str:
        return self.key.isoformat() if isinstance(self.key, dt.date) else f"d{self.key}"


_ISO_DATE = re.compile(r"\d{4}-\d{2}-\d{2}")


def _parse_date(text: str, where: str) -> dt.date:
    try:
        if not _ISO_DATE.fullmatch(str(text)):
            raise ValueError(text)
        return dt.date.fromisoformat(str(text))
    except ValueError as exc:
        raise ConfigError(f"config key {where}: expected an ISO date YYYY-MM-DD, found {text!r}") from exc


def _parse_int(text: str, where: str) -> int:
    try:
        return int(text)
    except ValueError as exc:
        raise ConfigError(f"config key {where}: expected a day number (an integer), found {text!r}") from exc


def _shown(text: str | int) -> str:
    """A configured day as the config holds it: a quoted ISO date, or a bare day number."""
    return str(text) if isinstance(text, int) or str(text).isdigit() else repr(text)


def _segments(split: Split, *, dataset: str, n_days: int | None) -> list[tuple]:
    """[(first, last)] of the training and the test segment, checked (dates, or day numbers with `n_days`).

    Raises:
        ConfigError: naming the key (``datasets.<dataset>.split.train[1]``), the form expected and the value
            found, for an invalid date or day number, a reversed segment, or a test segment that does not start
            after the training segment ends.
    """
    bounds = []
    for name, seg in split.segments().items():
        key = f"datasets.{dataset}.split.{name}"
        ends = []
        for i, text in enumerate((seg.first, seg.last)):
            if n_days is None:
                ends.append(_parse_date(text, f"{key}[{i}]"))
                continue
            v = _parse_int(text, f"{key}[{i}]")
            if not 0 <= v < n_days:
                raise ConfigError(f"config key {key}[{i}]: expected a day number in 0..{n_days - 1} "
                                  f"(datasets.{dataset}.n_days: {n_days}), found {v}")
            ends.append(v)
        if ends[1] < ends[0]:
            raise ConfigError(f"config key {key}: expected [first, last] with first <= last, found "
                              f"[{_shown(seg.first)}, {_shown(seg.last)}]")
        bounds.append(tuple(ends))
    if bounds[1][0] <= bounds[0][1]:
        last = bounds[0][1]
        raise ConfigError(f"config key datasets.{dataset}.split.test[0]: expected a day after the last training "
                          f"day {_shown(last if isinstance(last, int) else last.isoformat())} "
                          f"(datasets.{dataset}.split.train[1]; the test segment follows the training segment "
                          f"without overlap), found {_shown(split.test[0])}")
    return bounds


def calendar_days(split: Split, *, dataset: str) -> list[Day]:
    """All tensor days: training segment then test segment (inclusive ranges of dates).

    Raises:
        ConfigError: an invalid date, a reversed segment, or a test segment that does not start after training
            ends (see `_segments`).
    """
    out: list[Day] = []
    for name, (a, b) in zip(("train", "test"), _segments(split, dataset=dataset, n_days=None)):
        for k in range((b - a).days + 1):
            out.append(Day(index=len(out), key=a + dt.timedelta(days=k), split=name))
    return out


def numbered_days(split: Split, *, dataset: str, n_days: int) -> list[Day]:
    """Tensor days for a dataset with numbered days (YJMob d = 0..n_days-1)."""
    out: list[Day] = []
    for name, (a, b) in zip(("train", "test"), _segments(split, dataset=dataset, n_days=n_days)):
        base = len(out)
        out.extend([Day(index=base + k, key=a + k, split=name) for k in range(b - a + 1)])
    return out


def configured_days(cfg, dataset: str) -> list[Day]:
    """The tensor days of a dataset's typed section (dates, or YJMob's day numbers)."""
    n_days = getattr(cfg, "n_days", None)
    if n_days is None:
        return calendar_days(cfg.split, dataset=dataset)
    return numbered_days(cfg.split, dataset=dataset, n_days=n_days)


def _allowance_key(text: str | int, where: str, numbered: bool) -> dt.date | int:
    return _parse_int(str(text), where) if numbered else _parse_date(str(text), where)


def allowed_empty(cfg) -> set:
    """The day keys (dates, or day numbers) of ``allow_empty_days``, already checked by `check_days`."""
    numbered = getattr(cfg, "n_days", None) is not None
    return {_allowance_key(v, "allow_empty_days", numbered) for v in cfg.allow_empty_days}


def check_days(cfg, dataset: str) -> None:
    """Parse-time checks of a dataset's split, evaluation days and empty-day allowance.

    Runs when the typed section is built (``prep.config``), so a mistake stops the workflow when settings are
    resolved, before any job: the split (`_segments`), every ``test_positions`` position inside the test
    segment, and ``allow_empty_days``: every entry a day of the segments and never an evaluation day (the
    positions, or the calendar's first weekdays / weekend days; for YJMob's recovered week, any test day).

    Raises:
        ConfigError: naming the key, the form expected and the value found.
    """
    days = configured_days(cfg, dataset)
    test = [d for d in days if d.split == "test"]
    known = True  # the evaluation days follow from the config alone
    for name in ("id", "ood"):
        rule: EvalRule = getattr(cfg.eval_days, name)
        if rule.rule != "test_positions":
            known = known and isinstance(days[0].key, dt.date)  # YJMob: the week comes from the data
            continue
        key = f"datasets.{dataset}.eval_days.{name}.values"
        span = f"0..{len(test) - 1} ({len(test)} days: {test[0].label}..{test[-1].label})"
        if not rule.values:
            raise ConfigError(f"config key {key}: expected at least one position in the test segment, {span}, "
                              f"found []")
        for i, v in enumerate(rule.values):
            if not 0 <= v < len(test):
                raise ConfigError(f"config key {key}[{i}]: expected a position in the test segment, {span}, "
                                  f"found {v}")
    eval_of: dict[int, str] = {}  # tensor day -> "id" / "ood", where the config alone fixes it
    for name in ("id", "ood") if known else ():
        rule = getattr(cfg.eval_days, name)
        if rule.rule == "test_positions":
            picked = [test[v].index for v in rule.values]
        else:  # calendar weekends; too few matching days is left to pick_eval_days at preparation
            want = rule.rule == "first_weekend"
            picked = [d.index for d in test if (d.key.weekday() >= 5) == want][: rule.count]
        eval_of.update({i: name for i in picked})
    numbered = not isinstance(days[0].key, dt.date)
    by_key = {d.key: d for d in days}
    segs = ", ".join(f"{s[0].label}..{s[-1].label}" for s in
                     ([d for d in days if d.split == "train"], test))
    for i, text in enumerate(cfg.allow_empty_days):
        key = f"datasets.{dataset}.allow_empty_days[{i}]"
        day = by_key.get(_allowance_key(text, key, numbered))
        if day is None:
            raise ConfigError(f"config key {key}: expected a day of the training or test segment ({segs}), "
                              f"found {_shown(text)}")
        if day.index in eval_of:
            raise ConfigError(f"config key {key}: expected a day that is not an evaluation day (an evaluation day "
                              f"may never be empty), found {_shown(text)}, a datasets.{dataset}.eval_days."
                              f"{eval_of[day.index]} day")
        if not known and day.split == "test":
            raise ConfigError(f"config key {key}: expected a training day (an evaluation day may never be empty, "
                              f"and a first_weekdays/first_weekend rule of datasets.{dataset}.eval_days picks test "
                              f"days by the week recovered from the data, so any test day may be one), found "
                              f"{_shown(text)}")


def refuse_empty_days(dataset: str, days: list[Day], has_data: Sequence[bool], allowed: set, files: Sequence[Path],
                      *, what: str, expected: str) -> list[str]:
    """Every configured day must have data, unless ``datasets.<dataset>.allow_empty_days`` lists it.

    Args:
        dataset: dataset name; days: the tensor days; has_data: per tensor day, whether any record was read.
        allowed: day keys of the allowance (`allowed_empty`); files: the raw files read.
        what: what a day lacks ("record", "session", "line in the crop"); expected: what was expected instead.
    Returns:
        Labels of the empty days the allowance accepts (meta.json ``empty_days``).
    Raises:
        PrepError: naming the empty days that are not allowed and the files read.
    """
    empty = [d for d in days if not has_data[d.index]]
    bad = [d.label for d in empty if d.key not in allowed]
    if bad:
        raise PrepError(f"{dataset}: no {what} for day(s) {bad} of the configured segments, in the "
                        f"{describe_files(files)}; expected {expected}, or the day(s) listed in "
                        f"datasets.{dataset}.allow_empty_days")
    return [d.label for d in empty]


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
