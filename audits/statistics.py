"""Statistics family, part 1: normalization and intensity alignment recomputed from the RAW training segment.

The raw files named in meta.json (checked by SHA-256) are read again through the `prep` readers; the audit
then computes, with its own code, the training 99th percentile, the training mean of normalized demand and
kappa, and compares them with meta.json and with the values in demand.parquet. The same quantities over all
days and over the test segment are computed too, to name the leak when a stored value matches one of them.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from audits.context import AuditContext, AuditInputError
from audits.report import Check

RTOL = 1e-6
"""Relative tolerance of a recomputed statistic (float64 recomputation of the same numbers)."""
TENSOR_RTOL, TENSOR_ATOL = 1e-5, 1e-6
"""Tolerance of demand.parquet against raw / p99 * kappa (the tensor is stored as float32)."""
TOLERANCE = (f"statistics: relative {RTOL:g}; demand.parquet entries: |stored - expected| <= "
             f"{TENSOR_ATOL:g} + {TENSOR_RTOL:g} |expected| (float32 storage)")


def close(a: float | None, b: float | None, rtol: float = RTOL) -> bool:
    """|a - b| <= rtol * max(|a|, |b|) (exact equality for zeros); False when either is missing."""
    if a is None or b is None:
        return False
    a, b = float(a), float(b)
    return abs(a - b) <= rtol * max(abs(a), abs(b)) or a == b


@dataclass(frozen=True, kw_only=True)
class Recomputed:
    """Statistics of one dataset recomputed from its raw files, per day set."""

    values: np.ndarray  # (D, 144, R, C) float64 raw units, meta day order
    train: np.ndarray  # tensor day indices of the training segment (from the settings)
    test: np.ndarray
    p99: dict[str, float]  # {"train", "all", "test"}
    mean_norm: dict[str, float]  # mean of values / p99_train over {"train", "all", "test"} days


def recompute(ctx: AuditContext, ds: str) -> Recomputed:
    """Rebuilds the raw crop (prep readers) and recomputes p99 and normalized means (cached on ctx)."""
    cache = ctx.cache.setdefault("statistics.recompute", {})
    if ds in cache:
        return cache[ds]
    raw = ctx.raw(ds)
    meta = ctx.meta(ds)
    index = {d["label"]: d["index"] for d in meta["days"]}
    order = np.empty(len(raw.days), dtype=np.int64)
    for i, d in enumerate(raw.days):
        if d.label not in index:
            raise AuditInputError(f"{ctx.rel(ctx.meta_path(ds))}: the raw files hold day {d.label}, which "
                                  f"meta.json does not list")
        order[index[d.label]] = i
    if len(raw.days) != len(meta["days"]):
        raise AuditInputError(f"{ctx.rel(ctx.meta_path(ds))}: lists {len(meta['days'])} days, the raw files "
                              f"rebuild {len(raw.days)}")
    values = np.asarray(raw.values, dtype=np.float64)[order]
    train, test = ctx.train_index(ds), ctx.test_index(ds)
    q = ctx.percentile
    sets = {"train": train, "all": np.arange(values.shape[0]), "test": test}
    p99 = {k: float(np.percentile(values[v].ravel(), q)) for k, v in sets.items()}
    mean_norm = {k: float((values[v] / p99["train"]).mean()) for k, v in sets.items()}
    out = Recomputed(values=values, train=train, test=test, p99=p99, mean_norm=mean_norm)
    cache[ds] = out
    return out


def check_p99(ctx: AuditContext) -> Check:
    """Stored p99 equals the raw training segment's percentile."""
    chk = Check(id="statistics.p99", family="statistics", tolerance=TOLERANCE,
                claim="The normalizer p99 in meta.json equals the percentile recomputed from the raw files' "
                      "TRAINING segment (read again through the prep readers).")
    for ds in ctx.datasets:
        try:
            r, meta = recompute(ctx, ds), ctx.meta(ds)
        except AuditInputError as exc:
            chk.fail(f"{exc} — p99 cannot be verified")
            continue
        where = ctx.rel(ctx.meta_path(ds))
        stored = meta.get("p99")
        if not close(stored, r.p99["train"]):
            named = [k for k in ("all", "test") if close(stored, r.p99[k]) and not close(r.p99[k], r.p99["train"])]
            leak = {"all": "p99 computed on all days", "test": "p99 computed on the test segment"}
            chk.fail(f"{where}: p99 = {stored!r}, but the {ctx.percentile:g}th percentile of the raw TRAINING "
                     f"segment is {r.p99['train']:.9g}" + (f" — it equals the {named[0]}-days value: "
                                                           f"{leak[named[0]]}" if named else ""))
        if not close(meta.get("p99_all_days"), r.p99["all"]):
            chk.fail(f"{where}: p99_all_days = {meta.get('p99_all_days')!r}, recomputed {r.p99['all']:.9g}")
        chk.evidence[ds] = {"stored": stored, "train": r.p99["train"], "all_days": r.p99["all"],
                            "test": r.p99["test"], "train_days": len(r.train)}
    return chk


def expected_kappa(ctx: AuditContext, ds: str) -> dict[str, float]:
    """kappa and its inputs recomputed from raw files: reference mean / training mean (1 for the reference).

    Returns:
        {"kappa", "reference_mean", "train_mean", "kappa_if_test", "kappa_if_all"}: the last two are what kappa
        would be with the dataset's mean taken over the test segment or over all days (to name a leak).
    """
    ref = ctx.kappa_reference
    mine = recompute(ctx, ds)
    ref_mean = recompute(ctx, ref).mean_norm["train"]
    if ds == ref:
        return {"kappa": 1.0, "reference_mean": ref_mean, "train_mean": ref_mean,
                "kappa_if_test": ref_mean / mine.mean_norm["test"], "kappa_if_all": ref_mean / mine.mean_norm["all"]}
    return {"kappa": ref_mean / mine.mean_norm["train"], "reference_mean": ref_mean,
            "train_mean": mine.mean_norm["train"], "kappa_if_test": ref_mean / mine.mean_norm["test"],
            "kappa_if_all": ref_mean / mine.mean_norm["all"]}


def check_kappa(ctx: AuditContext) -> Check:
    """Stored kappa (and its inputs) equal the raw training-segment recomputation."""
    chk = Check(id="statistics.kappa", family="statistics", tolerance=TOLERANCE,
                claim="kappa = reference training mean / training mean of normalized demand, recomputed from the "
                      "raw TRAINING segments of the dataset and of the reference dataset, equals meta.json.")
    for ds in ctx.datasets:
        try:
            k, meta = expected_kappa(ctx, ds), ctx.meta(ds)
        except AuditInputError as exc:
            chk.fail(f"{exc} — kappa cannot be verified")
            continue
        where = ctx.rel(ctx.meta_path(ds))
        stored = meta.get("kappa")
        if not close(stored, k["kappa"]):
            hint = ""
            if close(stored, k["kappa_if_test"]):
                hint = " — it equals the value from the TEST segment's mean: kappa from the test segment"
            elif close(stored, k["kappa_if_all"]):
                hint = " — it equals the value from the all-days mean: kappa computed on all days"
            chk.fail(f"{where}: kappa = {stored!r}, recomputed from the training segments {k['kappa']:.9g}{hint}")
        for key, want in (("train_mean_normalized", k["train_mean"]), ("kappa_reference_mean", k["reference_mean"])):
            if not close(meta.get(key), want):
                chk.fail(f"{where}: {key} = {meta.get(key)!r}, recomputed from the raw training segment {want:.9g}")
        chk.evidence[ds] = {"stored": stored, **k, "reference": ctx.kappa_reference}
    return chk


def check_tensor(ctx: AuditContext) -> Check:
    """demand.parquet = raw / p99_train * kappa, entry by entry."""
    chk = Check(id="statistics.tensor", family="statistics", tolerance=TOLERANCE,
                claim="Every entry of demand.parquet (what the environment serves) equals raw demand / training "
                      "p99 x training kappa, recomputed from the raw files.")
    for ds in ctx.datasets:
        try:
            r, k, t = recompute(ctx, ds), expected_kappa(ctx, ds), ctx.tensor(ds)
        except AuditInputError as exc:
            chk.fail(f"{exc} — the tensor cannot be verified")
            continue
        where = ctx.rel(ctx.tensor_path(ds))
        stored = t.demand.astype(np.float64)
        if stored.shape != r.values.shape:
            chk.fail(f"{where}: shape {stored.shape}, the raw crop rebuilds {r.values.shape}")
            continue
        scale = k["kappa"] / r.p99["train"]
        want = r.values * scale
        err = np.abs(stored - want)
        bad = err > TENSOR_ATOL + TENSOR_RTOL * np.abs(want)
        den = float((r.values ** 2).sum())
        implied = float((stored * r.values).sum() / den) if den > 0 else float("nan")
        if bad.any():
            d, s, row, col = (int(v) for v in np.argwhere(bad)[0])
            label = ctx.meta(ds)["days"][d]["label"]
            alt = {"p99 over all days": k["kappa"] / r.p99["all"],
                   "kappa from the test segment": k["kappa_if_test"] / r.p99["train"],
                   "kappa from all days": k["kappa_if_all"] / r.p99["train"]}
            named = [n for n, v in alt.items() if close(implied, v, 1e-4) and not close(v, scale, 1e-4)]
            chk.fail(f"{where}: {int(bad.sum())} entries differ from raw / p99_train x kappa (first: day {label}, "
                     f"slot {s}, row {row}, col {col}: stored {stored[d, s, row, col]:.7g}, expected "
                     f"{want[d, s, row, col]:.7g}); the stored tensor is raw x {implied:.7g}, expected raw x "
                     f"{scale:.7g}" + (f" — it matches {named[0]}" if named else ""))
        chk.evidence[ds] = {"entries": int(want.size), "max_abs_error": float(err.max()),
                            "scale_expected": scale, "scale_implied": implied, "entries_off": int(bad.sum())}
    return chk


def check_not_all_days(ctx: AuditContext) -> Check:
    """Where the training and all-days values differ, no stored statistic equals the all-days one."""
    chk = Check(id="statistics.not_all_days", family="statistics", tolerance=TOLERANCE,
                claim="No stored statistic (p99, training mean, kappa) equals its all-days value where the "
                      "training and all-days values differ; where they coincide the dataset cannot tell.")
    for ds in ctx.datasets:
        try:
            r, k, meta = recompute(ctx, ds), expected_kappa(ctx, ds), ctx.meta(ds)
        except AuditInputError as exc:
            chk.fail(f"{exc} — cannot be verified")
            continue
        where = ctx.rel(ctx.meta_path(ds))
        rows = {"p99": (meta.get("p99"), r.p99["train"], r.p99["all"]),
                "train_mean_normalized": (meta.get("train_mean_normalized"), r.mean_norm["train"], r.mean_norm["all"]),
                "kappa": (meta.get("kappa"), k["kappa"], k["kappa_if_all"])}
        ev = {}
        for name, (stored, train, alld) in rows.items():
            distinct = not close(train, alld)
            ev[name] = {"stored": stored, "train": train, "all_days": alld, "distinguishable": distinct}
            if distinct and close(stored, alld):
                chk.fail(f"{where}: {name} = {stored!r} equals its ALL-DAYS value {alld:.9g} (training value "
                         f"{train:.9g}) — {name} computed on all days, test days included")
        chk.evidence[ds] = ev
    return chk
