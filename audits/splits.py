"""Splits family: the temporal split and the evaluation days, against the settings of config.yaml.

* `check_segments`: meta.json's days are exactly the configured training segment then the test segment, each
  day marked with the segment config puts it in; the two are disjoint and every training day precedes every
  test day; the tensor holds exactly those days.
* `check_eval_days`: the ID and OOD days lie in the test segment, are disjoint and equal the days the
  configured rules pick.
"""
from __future__ import annotations

import datetime as dt

import numpy as np

from audits.context import AuditContext, AuditInputError, label_order, label_range
from audits.report import Check


def check_segments(ctx: AuditContext) -> Check:
    """Training and test segments: configured, disjoint, training strictly before test."""
    chk = Check(id="splits.segments", family="splits",
                claim="Every dataset's days are the configured training segment followed by the configured test "
                      "segment, disjoint, every training day before every test day; the tensor holds those days.")
    for ds in ctx.datasets:
        try:
            meta = ctx.meta(ds)
        except AuditInputError as exc:
            chk.fail(str(exc))
            continue
        where = ctx.rel(ctx.meta_path(ds))
        expected = ctx.calendar(ds)
        want = dict(expected)
        days = meta.get("days", [])
        labels = [d["label"] for d in days]
        for pos, d in enumerate(days):
            if d.get("index") != pos:
                chk.fail(f"{where}: days[{pos}] has index {d.get('index')}; expected {pos} (position = tensor day)")
            seg = want.get(d["label"])
            if seg is None:
                chk.fail(f"{where}: day {d['label']} (index {pos}) lies in no configured segment "
                         f"(datasets.{ds}.split = {ctx.split_cfg(ds)})")
            elif d.get("split") != seg:
                chk.fail(f"{where}: day {d['label']} (index {pos}) is marked {d.get('split')!r} but lies in the "
                         f"configured {seg} segment {ctx.split_cfg(ds)[seg]} — "
                         f"{'a test day moved into training' if seg == 'test' else 'a training day moved into test'}")
        missing = [lab for lab, _ in expected if lab not in set(labels)]
        if missing:
            chk.fail(f"{where}: configured day(s) {missing[:5]}{'...' if len(missing) > 5 else ''} are absent")
        if labels != [lab for lab, _ in expected if lab in set(labels)]:
            chk.fail(f"{where}: days are not in calendar order (training segment, then test segment)")
        train = [d["label"] for d in days if d.get("split") == "train"]
        test = [d["label"] for d in days if d.get("split") == "test"]
        both = sorted(set(train) & set(test))
        if both:
            chk.fail(f"{where}: day(s) {both} are in both the training and the test segment")
        if train and test and max(map(label_order, train)) >= min(map(label_order, test)):
            late = max(train, key=label_order)
            chk.fail(f"{where}: training day {late} does not precede test day {min(test, key=label_order)} "
                     f"(temporal split violated)")
        stored = {k: list(v) for k, v in meta.get("split", {}).items()}
        cfg = {k: [str(v[0]), str(v[1])] for k, v in ctx.split_cfg(ds).items()}
        cfg_labels = {k: [label_range(*v)[0], label_range(*v)[-1]] for k, v in cfg.items()}
        if stored != cfg_labels:
            chk.fail(f"{where}: split {stored} differs from config datasets.{ds}.split {cfg_labels}")
        n_tensor = _tensor_days(ctx, ds, chk)
        chk.evidence[ds] = {"train": [train[0], train[-1], len(train)] if train else [],
                            "test": [test[0], test[-1], len(test)] if test else [],
                            "configured": cfg_labels, "tensor_days": n_tensor}
    return chk


def _tensor_days(ctx: AuditContext, ds: str, chk: Check) -> int | None:
    """Number of days of the loaded tensor (must equal the number of meta days)."""
    try:
        t = ctx.tensor(ds)
    except AuditInputError as exc:
        chk.fail(str(exc))
        return None
    n = int(t.demand.shape[0])
    if n != len(ctx.meta(ds)["days"]):
        chk.fail(f"{ctx.rel(ctx.tensor_path(ds))}: holds {n} days, meta.json lists {len(ctx.meta(ds)['days'])}")
    return n


def weekend_flags(ctx: AuditContext, ds: str) -> dict[str, bool]:
    """{label: weekend} recomputed: Sat/Sun from the date, or pseudo-weekend from the recovered week (YJMob)."""
    meta = ctx.meta(ds)
    out = {}
    week = meta.get("week")
    for d in meta["days"]:
        lab = d["label"]
        if lab.startswith("d"):
            if not week:
                raise AuditInputError(f"{ctx.rel(ctx.meta_path(ds))}: numbered days need the recovered week, "
                                      f"found week = {week!r}")
            out[lab] = (int(lab[1:]) % int(week["lag"])) in set(week["pseudo_weekend_phases"])
        else:
            out[lab] = dt.date.fromisoformat(lab).weekday() >= 5
    return out


def expected_eval_days(ctx: AuditContext, ds: str) -> dict[str, list[int]]:
    """ID/OOD tensor day indices picked by the configured rules from the config-derived test segment."""
    meta = ctx.meta(ds)
    index = {d["label"]: d["index"] for d in meta["days"]}
    test = [lab for lab, s in ctx.calendar(ds) if s == "test"]
    weekend = weekend_flags(ctx, ds)
    out = {}
    for name in ("id", "ood"):
        rule = getattr(ctx.section(ds).eval_days, name)
        if rule.rule == "test_positions":
            picked = [test[v] for v in rule.values]
        else:
            want = rule.rule == "first_weekend"
            picked = [lab for lab in test if weekend.get(lab) == want][: rule.count]
        out[name] = sorted(index[lab] for lab in picked if lab in index)
    return out


def check_eval_days(ctx: AuditContext) -> Check:
    """ID and OOD days: in the test segment, disjoint, equal to the configured ones."""
    chk = Check(id="splits.eval_days", family="splits",
                claim="ID and OOD evaluation days lie in the test segment, are disjoint and equal the days the "
                      "configured rules pick.")
    for ds in ctx.datasets:
        try:
            meta = ctx.meta(ds)
            expected = expected_eval_days(ctx, ds)
        except (AuditInputError, KeyError, IndexError) as exc:
            chk.fail(f"{ctx.rel(ctx.meta_path(ds))}: cannot derive the configured eval days ({exc})")
            continue
        where = ctx.rel(ctx.meta_path(ds))
        labels = {d["index"]: d["label"] for d in meta["days"]}
        test = set(ctx.test_index(ds).tolist())
        stored = {k: [int(i) for i in v] for k, v in meta.get("eval_days", {}).items()}
        for name in ("id", "ood"):
            got = stored.get(name, [])
            outside = [i for i in got if i not in test]
            if outside:
                chk.fail(f"{where}: eval_days.{name} holds day(s) {[labels.get(i, i) for i in outside]} "
                         f"(indices {outside}) outside the test segment — evaluation on non-test days")
            if sorted(got) != expected[name]:
                chk.fail(f"{where}: eval_days.{name} = {[labels.get(i, i) for i in got]}, the configured rule "
                         f"picks {[labels[i] for i in expected[name]]}")
        overlap = sorted(set(stored.get("id", [])) & set(stored.get("ood", [])))
        if overlap:
            chk.fail(f"{where}: ID and OOD days overlap: {[labels.get(i, i) for i in overlap]}")
        chk.evidence[ds] = {k: [labels.get(i, i) for i in v] for k, v in stored.items()} | {
            "expected": {k: [labels[i] for i in v] for k, v in expected.items()},
            "test_days": int(np.size(ctx.test_index(ds)))}
    return chk
