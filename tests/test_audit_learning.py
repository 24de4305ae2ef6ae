"""The learning part of the leakage audit (`protocol.learning_days`, the `audit_learning` rule): on a tree holding
learning runs as `snakemake learning` writes them (manifest, snapshot index, curve), the check passes, and it fails,
naming the file and the day, on a curve that scores a test day or a day its run trained on, on a run that trained on
a validation day, on validation days that are not the last training days, and on a snapshot that changed after
training; the tables' report leaves the runs out, and the `learning` target's gate refuses a changed curve."""
from __future__ import annotations

import hashlib
import json
import os
import runpy
import shutil
import sys
from pathlib import Path
from types import SimpleNamespace

import polars as pl
import pytest

from audit_fixtures import fixture_config
from audits.context import AuditContext
from audits.learning import LEARNING_LEFT_OUT, check_learning_days
from audits.report import write_report
from audits.runner import report_identity, run_audit
from dswm.settings import param, resolve

ROOT = Path(__file__).resolve().parents[1]
TRAIN = ["2013-11-01", "2013-11-02", "2013-11-03", "2013-11-04"]  # the fixture config's Milan training segment
TEST = ["2013-12-21", "2013-12-22"]
VALIDATION = TRAIN[-2:]


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def curve_rows(run: Path, days: list[int], labels: list[str], snapshots: list[tuple[str, str]]) -> pl.DataFrame:
    """The rows a learning_score job writes: each snapshot (path, SHA-256) on each day."""
    return pl.DataFrame([{"day": d, "label": labels[d], "split": "validation", "sr_mean": 0.6 + 0.01 * i,
                          "snapshot": f"{run.relative_to(run.parents[4])}/snapshots/{name}", "snapshot_sha256": h}
                         for i, (name, h) in enumerate(snapshots) for d in days]).with_columns(
        pl.col("day").cast(pl.Int32))


def write_learner(root: Path, method: str, *, train_days=(0, 1), validation=VALIDATION) -> Path:
    """A learning run of ``method`` on Milan seed 0: two day episodes of 143 transitions per training day, an
    untrained and a final snapshot, scored on the validation days."""
    labels = TRAIN + TEST
    run = root / "results" / "learning" / "milan" / method / "seed0"
    (run / "snapshots").mkdir(parents=True)
    days = [d for d in train_days for _ in range(2)]
    snaps = []
    for name in ("snapshot_untrained_of10.pt", "snapshot_0010of10.pt"):
        (run / "snapshots" / name).write_bytes(f"{method} {name}".encode())
        snaps.append((name, sha(run / "snapshots" / name)))
    (run / "snapshots" / "index.json").write_text(json.dumps(
        {"method": method, "seed": 0, "snapshots": [{"file": n, "sha256": h} for n, h in snaps]}))
    (run / "train_manifest.json").write_text(json.dumps(
        {"days": days, "day_labels": [labels[d] for d in days], "n_transitions": 143 * len(days),
         "transitions_per_day_episode": 143, "validation_days": list(validation), "read_test_data": False}))
    val = [labels.index(v) for v in validation]
    curve_rows(run, val, labels, snaps).write_parquet(run / "curve.parquet")
    return run


def write_reference(root: Path, method: str, days: list[int]) -> Path:
    labels = TRAIN + TEST
    run = root / "results" / "learning" / "milan" / method / "seed0"
    run.mkdir(parents=True)
    pl.DataFrame([{"day": d, "label": labels[d], "split": "validation", "sr_mean": 0.7} for d in days]).with_columns(
        pl.col("day").cast(pl.Int32)).write_parquet(run / "curve.parquet")
    return run


@pytest.fixture
def learned(tmp_path):
    """A tree with Milan's meta.json (days 0-3 training, 4-5 test), two learners' runs and Static's scores."""
    settings = resolve(fixture_config())
    data = tmp_path / "results" / "data" / "milan"
    data.mkdir(parents=True)
    (data / "meta.json").write_text(json.dumps(
        {"dataset": "milan", "days": [{"index": i, "label": lab} for i, lab in enumerate(TRAIN + TEST)]}))
    write_learner(tmp_path, "ppo")
    write_learner(tmp_path, "sac")
    write_reference(tmp_path, "static", [2, 3])
    return tmp_path, settings


def check(root: Path, settings):
    return check_learning_days(AuditContext(root=root, settings=settings))


def test_learning_runs_on_their_validation_days_pass_with_their_evidence(learned):
    root, settings = learned
    chk = check(root, settings)
    assert chk.passed, chk.failures
    ppo = chk.evidence["runs"]["milan/ppo/seed0"]
    assert ppo == {"validation_days": VALIDATION, "training_records": 4, "distinct_training_days": 2,
                   "curve_rows": 4, "snapshots_hashed": 2}
    assert chk.evidence["runs"]["milan/static/seed0"]["curve_rows"] == 2


def test_a_curve_row_on_a_test_day_fails_naming_the_file_and_the_day(learned):
    root, settings = learned
    curve = root / "results/learning/milan/static/seed0/curve.parquet"
    df = pl.read_parquet(curve)
    pl.concat([df, df.head(1).with_columns(pl.lit(4, pl.Int32).alias("day"), pl.lit(TEST[0]).alias("label"))]
              ).write_parquet(curve)
    chk = check(root, settings)
    assert chk.failures == ["results/learning/milan/static/seed0/curve.parquet: scores day 2013-12-21 (index 4), a "
                            "test day — a learning curve reads the test period"]


def test_a_curve_row_on_a_day_its_run_trained_on_fails(learned):
    root, settings = learned
    curve = root / "results/learning/milan/ppo/seed0/curve.parquet"
    df = pl.read_parquet(curve)
    pl.concat([df, df.head(1).with_columns(pl.lit(0, pl.Int32).alias("day"), pl.lit(TRAIN[0]).alias("label"))]
              ).write_parquet(curve)
    chk = check(root, settings)
    assert chk.failures == ["results/learning/milan/ppo/seed0/curve.parquet: scores training day 2013-11-01 (index 0), "
                            "which is not one of its run's validation days ['2013-11-03', '2013-11-04'] — its model "
                            "may have trained on it"]


def test_a_run_that_trained_on_a_validation_day_fails(learned):
    root, settings = learned
    shutil.rmtree(root / "results/learning/milan/sac/seed0")
    write_learner(root, "sac", train_days=(0, 1, 3))
    chk = check(root, settings)
    assert chk.failures == ["results/learning/milan/sac/seed0/train_manifest.json: training data holds validation "
                            "day(s) ['2013-11-04'] — its curve scores days it trained on"]


def test_validation_days_that_are_not_the_last_training_days_fail_and_the_references_are_held_to_the_learners(
        learned):
    root, settings = learned
    for method in ("ppo", "sac"):
        shutil.rmtree(root / "results/learning/milan" / method / "seed0")
        write_learner(root, method, train_days=(2, 3), validation=TRAIN[:2])
    chk = check(root, settings)
    early = [f for f in chk.failures if "the last 2 training day(s)" in f]
    assert [f.split(":")[0] for f in early] == [f"results/learning/milan/{m}/seed0/train_manifest.json"
                                               for m in ("ppo", "sac")]
    assert "['2013-11-03', '2013-11-04']" in early[0]
    assert ("results/learning/milan/static/seed0/curve.parquet: scores training day 2013-11-03 (index 2), which is "
            "not one of its run's validation days ['2013-11-01', '2013-11-02'] — its model may have trained on it"
            in chk.failures)


def test_a_snapshot_changed_after_training_or_one_outside_the_index_fails(learned):
    root, settings = learned
    run = root / "results/learning/milan/ppo/seed0"
    (run / "snapshots" / "snapshot_0010of10.pt").write_bytes(b"retrained")
    chk = check(root, settings)
    assert len(chk.failures) == 1 and chk.failures[0].startswith(
        "results/learning/milan/ppo/seed0/snapshots/snapshot_0010of10.pt: SHA-256 ")
    assert chk.failures[0].endswith("— the snapshot changed after training")
    df = pl.read_parquet(run / "curve.parquet")
    df.with_columns(pl.col("snapshot").str.replace("snapshot_0010of10", "snapshot_0005of10")).write_parquet(
        run / "curve.parquet")
    chk = check(root, settings)
    assert (f"results/learning/milan/ppo/seed0/curve.parquet: scores snapshot "
            f"results/learning/milan/ppo/seed0/snapshots/snapshot_0005of10.pt, which is not in its run's index "
            f"results/learning/milan/ppo/seed0/snapshots/index.json") in chk.failures


def test_the_tables_report_leaves_the_runs_out_and_the_learning_gate_refuses_a_changed_curve(learned):
    root, settings = learned
    tables = check_learning_days(AuditContext(root=root, settings=settings, read_learning=False))
    assert tables.passed and tables.evidence == {"note": LEARNING_LEFT_OUT}
    report = run_audit(root=root, settings=settings, scope="learning")
    assert report["passed"] and [c["id"] for c in report["checks"]] == ["protocol.learning_days",
                                                                        "read-only.unchanged"]
    read = [f["path"] for f in report["read_only"]["files"]]
    # meta.json; per learner its manifest, snapshot index, two snapshots and curve; Static's curve
    assert "results/learning/milan/static/seed0/curve.parquet" in read and len(read) == 12
    json_path = root / "results/audit/learning.json"
    write_report(report, json_path=json_path, md_path=json_path.with_suffix(".md"))

    def gate() -> SystemExit | None:
        stub = SimpleNamespace(log=[str(root / "logs" / "learning_check.log")],
                               input=SimpleNamespace(report=str(json_path)),
                               params=SimpleNamespace(audit=param(report_identity(settings)), target="learning"))
        Path(stub.log[0]).parent.mkdir(exist_ok=True)
        saved, cwd = sys.stderr, Path.cwd()
        try:
            os.chdir(root)
            runpy.run_path(str(ROOT / "workflow" / "scripts" / "target_gate.py"), init_globals={"snakemake": stub})
        except SystemExit as exc:
            return exc
        finally:
            sys.stderr.close()
            sys.stderr = saved
            os.chdir(cwd)
        return None

    assert gate() is None
    curve = root / "results/learning/milan/static/seed0/curve.parquet"
    before = sha(curve)
    pl.read_parquet(curve).with_columns(pl.lit(0.9).alias("sr_mean")).write_parquet(curve)
    assert isinstance(gate(), SystemExit)
    assert (root / "logs/learning_check.log").read_text().splitlines() == [
        f"learning refused: results/learning/milan/static/seed0/curve.parquet: SHA-256 is {sha(curve)}, "
        f"{json_path} vouches for {before} — the file changed after the audit; delete {json_path} and run "
        f"`snakemake --cores 2 learning --config profile=smoke` to audit the tree afresh"]
