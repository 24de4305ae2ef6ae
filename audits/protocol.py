"""Protocol family, part 1: every method is measured in the same world.

* `check_hashes`: every result file of every method carries one observation-spec hash, one eval-days hash
  and one scenario hash, each equal to the value recomputed from the settings and meta.json.
* `check_result_days`: every result file holds exactly the configured ID and OOD days of its dataset.

Part 2, that learners learn from training days only and evaluate the model they trained, is `audits.training`.
"""
from __future__ import annotations

from pathlib import Path

import polars as pl

from audits.context import AuditContext, AuditInputError
from audits.hashes import expected_hashes, expected_result_days
from audits.report import Check

HASH_COLUMNS = ("obs_spec_hash", "eval_days_hash", "scenario_hash")
RESULT_COLUMNS = ("day", "label", "split", "sr_mean", *HASH_COLUMNS, "seed", "method", "dataset")
HASH_LEAK = {"obs_spec_hash": "a different observation spec", "eval_days_hash": "different eval days",
                    "scenario_hash": "different scenario constants"}


def _read_result(ctx: AuditContext, path: Path) -> pl.DataFrame:
    try:
        return pl.read_parquet(ctx.ledger.track(path))
    except FileNotFoundError as exc:
        raise AuditInputError(f"{ctx.rel(path)}: result file missing (run the evaluate rule)") from exc
    except (OSError, pl.exceptions.PolarsError) as exc:
        raise AuditInputError(f"{ctx.rel(path)}: unreadable ({exc})") from exc


def result_path(ctx: AuditContext, ds: str, method: str, seed: int) -> Path:
    return ctx.run_dir(ds, method, seed) / "days.parquet"


def _results(ctx: AuditContext, chk: Check, ds: str):
    """(method, seed, path, table) of every result file of ``ds``; a missing or unreadable one fails ``chk``."""
    for method in ctx.methods:
        for seed in ctx.seeds(ds):
            path = result_path(ctx, ds, method, seed)
            try:
                df = _read_result(ctx, path)
            except AuditInputError as exc:
                chk.fail(str(exc))
                continue
            yield method, seed, path, df


def check_hashes(ctx: AuditContext) -> Check:
    """Same observation-spec, eval-days and scenario hashes in every result file, equal to the recomputed ones."""
    chk = Check(id="protocol.hashes", family="protocol",
                claim="Every result file of every method carries the observation-spec, eval-days and scenario "
                      "hashes recomputed from config.yaml and meta.json (one value per file).")
    for ds in ctx.datasets:
        try:
            want = expected_hashes(ctx, ds)
        except AuditInputError as exc:
            chk.fail(f"{exc} — the expected hashes cannot be recomputed")
            continue
        seen: dict[str, dict[str, list[str]]] = {c: {} for c in HASH_COLUMNS}
        for method, seed, path, df in _results(ctx, chk, ds):
            missing = [c for c in RESULT_COLUMNS if c not in df.columns]
            if missing:
                chk.fail(f"{ctx.rel(path)}: lacks column(s) {missing}")
                continue
            for col in ("dataset", "method", "seed"):
                vals = sorted(set(map(str, df[col].to_list())))
                own = {"dataset": ds, "method": method, "seed": str(seed)}[col]
                if vals != [own]:
                    chk.fail(f"{ctx.rel(path)}: column {col} holds {vals}, the path says {own!r}")
            for col in HASH_COLUMNS:
                vals = sorted(set(map(str, df[col].to_list())))
                for v in vals:
                    seen[col].setdefault(v, []).append(f"{method}/seed{seed}")
                if vals != [want[col]]:
                    chk.fail(f"{ctx.rel(path)}: {col} = {vals}, expected {want[col]} (recomputed from "
                             f"config.yaml and {ctx.rel(ctx.meta_path(ds))}) — {method} was run with "
                             f"{HASH_LEAK[col]}")
        chk.evidence[ds] = {"expected": want, "found": {c: {v: len(w) for v, w in s.items()} for c, s in seen.items()}}
    return chk


def check_result_days(ctx: AuditContext) -> Check:
    """Every result file evaluates exactly its dataset's configured ID and OOD days."""
    chk = Check(id="protocol.result_days", family="protocol",
                claim="Every result file holds exactly the configured ID and OOD days (as limited by the "
                      "profile), with their labels, and nothing else.")
    for ds in ctx.datasets:
        try:
            want = expected_result_days(ctx, ds)
            labels = {d["index"]: d["label"] for d in ctx.meta(ds)["days"]}
        except AuditInputError as exc:
            chk.fail(f"{exc} — the evaluated days cannot be verified")
            continue
        for method, seed, path, df in _results(ctx, chk, ds):
            if not {"day", "split"} <= set(df.columns):
                chk.fail(f"{ctx.rel(path)}: lacks the day/split columns")
                continue
            splits = sorted(set(df["split"].to_list()) - set(want))
            if splits:
                chk.fail(f"{ctx.rel(path)}: unknown split value(s) {splits}; expected id, ood")
            for split, days in want.items():
                got = sorted(int(d) for d in df.filter(pl.col("split") == split)["day"].to_list())
                if got != days:
                    chk.fail(f"{ctx.rel(path)}: split {split!r} evaluates days "
                             f"{[labels.get(d, d) for d in got]}, the configured {split.upper()} days are "
                             f"{[labels[d] for d in days]} — {method} evaluated on other days")
            if "label" in df.columns:
                wrong = [(int(d), lab) for d, lab in zip(df["day"].to_list(), df["label"].to_list())
                         if labels.get(int(d)) != lab]
                if wrong:
                    chk.fail(f"{ctx.rel(path)}: day index/label pairs {wrong[:3]} disagree with meta.json")
        chk.evidence[ds] = {k: [labels[d] for d in v] for k, v in want.items()}
    return chk
