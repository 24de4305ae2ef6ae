"""Protocol family, part 4: the learning curves score held-out training days only.

* `check_learning_days`: every learning run (``results/learning/<dataset>/<method>/seed<seed>/``,
  ``dswm.protocol.learning``, the `learning` target) trained on training days other than its validation days,
  which are the last training days in time order and never a test day; every score row of every curve there (the
  learners' and the reference methods') is of split ``validation`` on one of those days; and every snapshot a
  learner's row scores is a file of its run's snapshot index, hashing to the SHA-256 the index and the row record.

The tables' audit leaves these files out (its inputs stay the tables' sources); the learning audit
(results/audit/learning.json, the `audit_learning` rule, run by `learning` and `audit`) reads them.
"""
from __future__ import annotations

from pathlib import Path

import polars as pl

from audits.context import AuditContext, AuditInputError, label_order
from audits.report import Check
from audits.training import declares_no_test_data, manifest_days

LEARNING_LEFT_OUT = ("the learning runs are not read by this audit, whose inputs are the tables' sources alone: the "
                     "learning audit (results/audit/learning.json, the `audit_learning` rule, run by `learning` and "
                     "`audit`) checks their days")
"""The evidence note of the check in an audit that leaves the learning runs out (``AuditContext.read_learning``)."""


def learning_runs(ctx: AuditContext) -> list[Path]:
    """Every run directory under results/learning/ holding a training manifest or a curve (none in a tree where
    `learning` never ran)."""
    from dswm.protocol.learning import LEARNING_DIR, SCORE_FILE

    base = ctx.root / LEARNING_DIR
    if not base.is_dir():
        return []
    found = {p.parent for p in base.glob(f"*/*/seed*/{SCORE_FILE}")} | {p.parent for p in
                                                                       base.glob("*/*/seed*/train_manifest.json")}
    return sorted(found)


def _days_of(ctx: AuditContext, ds: str) -> tuple[dict[int, str], list[int], set[int]]:
    """({day index: label}, training days in time order, test days) of ``ds``, by the settings' split (computed once
    per audit)."""
    key = f"learning.days.{ds}"
    if key not in ctx.cache:
        labels = {int(d["index"]): d["label"] for d in ctx.meta(ds)["days"]}
        train = sorted((int(d) for d in ctx.train_index(ds)), key=lambda d: label_order(labels[d]))
        ctx.cache[key] = labels, train, {int(d) for d in ctx.test_index(ds)}
    return ctx.cache[key]


def _validation(chk: Check, ctx: AuditContext, ds: str, where: str, man: dict) -> list[int] | None:
    """The validation days a learner's manifest records, checked to be the last training days in time order."""
    labels, train, test = _days_of(ctx, ds)
    by_label = {lab: d for d, lab in labels.items()}
    recorded = man.get("validation_days")
    if not isinstance(recorded, list) or not recorded or not all(isinstance(x, str) for x in recorded):
        chk.fail(f"{where}: 'validation_days' is {recorded!r}; expected the labels of the held-out training days "
                 f"that score the run's snapshots")
        return None
    unknown = [lab for lab in recorded if lab not in by_label]
    if unknown:
        chk.fail(f"{where}: validation day(s) {unknown} are no day of meta.json of {ds}")
        return None
    val = [by_label[lab] for lab in recorded]
    tested = [labels[d] for d in val if d in test]
    if tested:
        chk.fail(f"{where}: validation day(s) {tested} are test days — a learning curve scored on them reads the "
                 f"test period")
    want = train[-len(val):] if len(val) < len(train) else None
    if want is None or sorted(val) != sorted(want):
        chk.fail(f"{where}: validation days {recorded}, but the last {len(val)} training day(s) in time order are "
                 f"{[labels[d] for d in want] if want else 'not enough to leave one that trains'} "
                 f"(dswm.protocol.learning.learning_days)")
    return val


def _curve(chk: Check, ctx: AuditContext, ds: str, path: Path, allowed: list[int] | None) -> pl.DataFrame | None:
    """A curve file's rows, each checked to be a validation row on a training day (on ``allowed`` when given)."""
    from dswm.protocol.learning import VALIDATION_SPLIT

    where = ctx.rel(path)
    try:
        df = pl.read_parquet(ctx.ledger.track(path))
    except (OSError, pl.exceptions.PolarsError) as exc:
        chk.fail(f"{where}: unreadable curve file ({exc})")
        return None
    missing = [c for c in ("day", "label", "split", "sr_mean") if c not in df.columns]
    if missing:
        chk.fail(f"{where}: a curve file without the column(s) {missing}; re-run its learning_score job")
        return None
    labels, train, test = _days_of(ctx, ds)
    split = df.filter(pl.col("split") != VALIDATION_SPLIT)
    if split.height:
        chk.fail(f"{where}: {split.height} row(s) of split {sorted(set(split['split'].to_list()))}; every score of a "
                 f"learning curve is of split {VALIDATION_SPLIT!r}")
    days = [int(d) for d in df["day"].to_list()]
    for d in sorted(set(days)):
        if d in test:
            chk.fail(f"{where}: scores day {labels[d]} (index {d}), a test day — a learning curve reads the test "
                     f"period")
        elif d not in train:
            chk.fail(f"{where}: scores day index {d}, which is no training day of {ds}")
        elif allowed is not None and d not in allowed:
            chk.fail(f"{where}: scores training day {labels[d]} (index {d}), which is not one of its run's "
                     f"validation days {[labels[v] for v in allowed]} — its model may have trained on it")
    wrong = [(d, lab) for d, lab in zip(days, df["label"].to_list()) if labels.get(d) != lab]
    if wrong:
        chk.fail(f"{where}: {len(wrong)} row(s) whose label is not meta.json's label of their day, e.g. day "
                 f"{wrong[0][0]} labelled {wrong[0][1]!r}")
    return df


def _snapshots(chk: Check, ctx: AuditContext, run: Path, df: pl.DataFrame) -> int:
    """Every snapshot a learner's curve scores is in its run's snapshot index and hashes as recorded; returns how
    many snapshot files were hashed."""
    where = ctx.rel(run / "curve.parquet")
    index_path = run / "snapshots" / "index.json"
    try:
        index = ctx.ledger.read_json(index_path)
        listed = {e["file"]: e["sha256"] for e in index["snapshots"]}
    except FileNotFoundError:
        chk.fail(f"{ctx.rel(index_path)}: missing, but {where} scores snapshots of this run")
        return 0
    except (ValueError, KeyError, TypeError) as exc:
        chk.fail(f"{ctx.rel(index_path)}: not a snapshot index ({exc!r}); re-run its learning_train job")
        return 0
    if not {"snapshot", "snapshot_sha256"} <= set(df.columns):
        chk.fail(f"{where}: without the columns snapshot and snapshot_sha256, its rows name no snapshot")
        return 0
    hashed = 0
    for name, sha in listed.items():
        path = run / "snapshots" / name
        try:
            now = ctx.ledger.sha256(path)
        except FileNotFoundError:
            chk.fail(f"{ctx.rel(path)}: listed in {ctx.rel(index_path)} but missing")
            continue
        hashed += 1
        if now != sha:
            chk.fail(f"{ctx.rel(path)}: SHA-256 {now}, but {ctx.rel(index_path)} records {sha} — the snapshot "
                     f"changed after training")
    for file, sha in sorted(set(zip(df["snapshot"].to_list(), df["snapshot_sha256"].to_list()))):
        path = Path(str(file)) if Path(str(file)).is_absolute() else ctx.root / str(file)  # relative to the root
        name = path.name
        if path.parent.resolve() != (run / "snapshots").resolve() or name not in listed:
            chk.fail(f"{where}: scores snapshot {file}, which is not in its run's index {ctx.rel(index_path)}")
        elif listed[name] != sha:
            chk.fail(f"{where}: scores {file} with SHA-256 {sha}, but {ctx.rel(index_path)} records {listed[name]}")
    return hashed


def check_learning_days(ctx: AuditContext) -> Check:
    """The learning curves train on training days other than their validation days and score those alone."""
    chk = Check(id="protocol.learning_days", family="protocol",
                claim="Every learning run under results/learning/ trained on training days only, none of them one of "
                      "its validation days; those are the last training days in time order, none a test day; every "
                      "row of every curve there (learners and references) is a validation row on one of them; and "
                      "every snapshot a curve scores is in its run's index and hashes as recorded.")
    if not ctx.read_learning:
        chk.evidence["note"] = LEARNING_LEFT_OUT
        return chk
    runs = learning_runs(ctx)
    if not runs:
        chk.evidence["note"] = "no learning run under results/learning/ (the `learning` target has not run)"
        return chk
    chk.evidence["runs"] = {}
    held: dict[str, dict[str, list[str]]] = {}
    curves: list[tuple[str, Path]] = []
    for run in runs:
        ds, method, seed_dir = run.parts[-3:]
        key = f"{ds}/{method}/{seed_dir}"
        manifest = run / "train_manifest.json"
        where = ctx.rel(manifest)
        try:
            if ds not in ctx.datasets:
                raise AuditInputError(f"{ctx.rel(run)}: a learning run of dataset {ds!r}, which this profile does not "
                                      f"prepare (run.datasets: {ctx.datasets})")
            labels = _days_of(ctx, ds)[0]
            if not manifest.is_file():  # a reference method's scores: checked with the learners' days below
                curves.append((ds, run / "curve.parquet"))
                continue
            man = ctx.ledger.read_json(manifest)
            val = _validation(chk, ctx, ds, where, man)
            days = manifest_days(chk, ctx, ds, man, where=where, method=method)
        except AuditInputError as exc:
            chk.fail(str(exc))
            continue
        except ValueError as exc:
            chk.fail(f"{where}: not valid JSON ({exc})")
            continue
        declares_no_test_data(chk, man, where)
        evidence = {"validation_days": man.get("validation_days")}
        if val is not None:
            held.setdefault(ds, {})[key] = sorted(labels[d] for d in val)
        if days is not None and val is not None:
            overlap = sorted({labels[d] for d in days} & {labels[d] for d in val})
            if overlap:
                chk.fail(f"{where}: training data holds validation day(s) {overlap} — its curve scores days it "
                         f"trained on")
            evidence.update(training_records=len(days), distinct_training_days=len(set(days)))
        curve = run / "curve.parquet"
        if curve.is_file():
            df = _curve(chk, ctx, ds, curve, val)
            if df is not None:
                evidence.update(curve_rows=df.height, snapshots_hashed=_snapshots(chk, ctx, run, df))
        else:
            evidence["curve_rows"] = "none yet: its learning_score job has not run"
        chk.evidence["runs"][key] = evidence
    for ds, runs_of in held.items():
        if len({tuple(v) for v in runs_of.values()}) > 1:
            chk.fail(f"results/learning/{ds}: the learners' validation days differ ({runs_of}); every curve of a "
                     f"dataset is scored on the same days")
    for ds, path in curves:
        sets = {tuple(v) for v in held.get(ds, {}).values()}
        allowed = None
        if len(sets) == 1:
            by_label = {lab: d for d, lab in _days_of(ctx, ds)[0].items()}
            allowed = [by_label[lab] for lab in next(iter(sets))]
        df = _curve(chk, ctx, ds, path, allowed)
        key = "/".join(path.parent.parts[-3:])
        chk.evidence["runs"][key] = {"reference": True, "curve_rows": None if df is None else df.height,
                                     "days_checked_against": "the learners' validation days" if allowed else
                                     "the training days (no learner's manifest on this dataset)"}
    return chk
