"""The extra part of the leakage audit (`protocol.extra_runs`, the `audit_extra` rule): on the clean tree with three
extra runs as extra_train and extra_evaluate leave them (a fleet-size variant that retrains DSWM, a do(s) variant
that evaluates the main model, Greedy under the fleet-size variant), the check passes; it fails, naming the file, on
an extra_train run that trained on a test day, on an evaluation that loaded another method's or variant's model, on
a model or result file changed after it was recorded; and the tables' report leaves the extra runs out."""
from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import polars as pl
import pytest

from audit_fixtures import clean, one_torch_thread, write_record  # noqa: F401 (fixtures)
from audits import extra
from audits.context import AuditContext
from audits.extra import EXTRA_LEFT_OUT, check_extra_runs

JOBS = [("milan", "K2", "dswm", 0, True), ("milan", "do2", "dswm", 0, False), ("milan", "K2", "greedy", 0, False)]


def sha(path: Path) -> str:
    import hashlib

    return hashlib.sha256(path.read_bytes()).hexdigest()


def extra_run(root: Path, variant: str, method: str) -> Path:
    return root / "results" / "extra" / "milan" / variant / method / "seed0"


def evaluate_into(root: Path, variant: str, method: str, record: dict | None = None) -> Path:
    """The main evaluation's result files of ``method`` written as the extra run's (its model ``record`` when
    given), with their content record."""
    from dswm.protocol.evaluation import read_method_record, read_model_record, write_days

    main = root / "results" / "milan" / method / "seed0"
    run = extra_run(root, variant, method)
    run.mkdir(parents=True, exist_ok=True)
    days = main / "days.parquet"
    write_days(pl.read_parquet(days), run / "days.parquet", record or read_model_record(days),
               read_method_record(days))
    shutil.copy2(main / "trajectory.npz", run / "trajectory.npz")
    write_record(run)
    return run / "days.parquet"


def retrain(root: Path, variant: str, method: str, days: list[int] | None = None) -> dict:
    """What extra_train leaves: the variant's own model.pt and train_manifest.json (the main run's manifest with
    this model's path and SHA-256, and ``days`` when given); returns the model record its evaluation stores."""
    main = root / "results" / "milan" / method / "seed0"
    run = extra_run(root, variant, method)
    run.mkdir(parents=True, exist_ok=True)
    (run / "model.pt").write_bytes(f"fixture model {method} under {variant}".encode())
    man = json.loads((main / "train_manifest.json").read_text())
    man.update(model=str((run / "model.pt").relative_to(root)), model_sha256=sha(run / "model.pt"))
    if days is not None:
        man.update(days=days, n_transitions=143 * len(days))
        man["day_labels"] = [d["label"] for i in days for d in json.loads(
            (root / "results/data/milan/meta.json").read_text())["days"] if d["index"] == i]
    (run / "train_manifest.json").write_text(json.dumps(man))
    return {"method": method, "train_source": method, "model": man["model"], "model_sha256": man["model_sha256"],
            "train_manifest": str((run / "train_manifest.json").relative_to(root))}


@pytest.fixture
def extras(clean, tmp_path):
    """A copy of the clean tree with the three extra runs of JOBS, and the audit's list of extra runs set to them."""
    root, settings = clean
    dst = tmp_path / "tree"
    shutil.copytree(root, dst)
    evaluate_into(dst, "K2", "dswm", retrain(dst, "K2", "dswm"))
    evaluate_into(dst, "do2", "dswm")
    evaluate_into(dst, "K2", "greedy")
    return dst, settings


def check(root, settings, **kw):
    return check_extra_runs(AuditContext(root=root, settings=settings, extra_runs=[list(j) for j in JOBS], **kw))


def test_the_extra_runs_pass_each_with_the_model_its_training_source_fitted(extras):
    chk = check(*extras)
    assert chk.passed, chk.failures
    runs = chk.evidence["runs"]
    assert runs["milan/K2/dswm/seed0"]["model"]["model"] == "results/extra/milan/K2/dswm/seed0/model.pt"
    assert runs["milan/K2/dswm/seed0"]["model"]["fitted_by"] == "extra_train"
    assert runs["milan/do2/dswm/seed0"]["model"] == {"model": "results/milan/dswm/seed0/model.pt",
                                                     "fitted_by": "train",
                                                     "training_days": "checked by protocol.training_days"}
    assert runs["milan/K2/greedy/seed0"] == {"content": "hashes as recorded", "model": {"model": None}}


def test_an_extra_train_run_on_a_test_day_fails_naming_the_day(extras):
    root, settings = extras
    meta = json.loads((root / "results/data/milan/meta.json").read_text())
    test = [d["index"] for d in meta["days"] if d["label"] >= "2013-12-21"]
    evaluate_into(root, "K2", "dswm", retrain(root, "K2", "dswm", days=[0, 1, test[0]]))
    chk = check(root, settings)
    label = next(d["label"] for d in meta["days"] if d["index"] == test[0])
    assert chk.failures == [f"results/extra/milan/K2/dswm/seed0/train_manifest.json: training data holds day(s) "
                            f"['{label}'] (indices [{test[0]}]) that are not training days — the replay/pre-collected "
                            f"data of dswm holds a test day"]


def test_an_evaluation_that_loaded_another_variants_model_fails(extras):
    root, settings = extras
    evaluate_into(root, "do2", "dswm", retrain(root, "K2", "dswm"))  # the do variant does not retrain: it must load the main model
    chk = check(root, settings)
    assert chk.failures == ["results/extra/milan/do2/dswm/seed0/days.parquet: model = "
                            "'results/extra/milan/K2/dswm/seed0/model.pt', expected results/milan/dswm/seed0/model.pt, "
                            "the model the main train job fitted"]


def test_a_model_or_result_file_changed_after_it_was_recorded_fails(extras):
    root, settings = extras
    model = extra_run(root, "K2", "dswm") / "model.pt"
    model.write_bytes(b"retrained behind the manifest's back")
    days = extra_run(root, "K2", "greedy") / "days.parquet"
    pl.read_parquet(days).with_columns(pl.lit(0.99).alias("sr_mean")).write_parquet(days)
    chk = check(root, settings)
    assert len(chk.failures) == 3, chk.failures
    assert chk.failures[0].startswith(f"results/extra/milan/K2/dswm/seed0/model.pt: SHA-256 is {sha(model)}, ")
    assert chk.failures[0].endswith("(model_sha256 of results/extra/milan/K2/dswm/seed0/train_manifest.json, which "
                                    "results/extra/milan/K2/dswm/seed0/days.parquet names) — not the model dswm "
                                    "trained; re-run its train job: `rm results/extra/milan/K2/dswm/seed0/model.pt`, "
                                    "then the same snakemake command again (or add `--forcerun "
                                    "results/extra/milan/K2/dswm/seed0/model.pt` to it)")
    assert chk.failures[1].startswith(f"results/extra/milan/K2/greedy/seed0/days.parquet: SHA-256 is {sha(days)}, ")
    assert "the result file changed after its evaluation; delete the result files of milan/K2/greedy/seed0" in (
        chk.failures[1])
    # ... and rewritten without the evaluation's metadata, it no longer says which model it loaded
    assert chk.failures[2].startswith("results/extra/milan/K2/greedy/seed0/days.parquet: no dswm.evaluated_model "
                                      "record in its metadata")


def test_the_tables_report_leaves_the_extra_runs_out_and_an_absent_run_is_listed_not_failed(extras):
    root, settings = extras
    left = check(root, settings, read_extra=False)
    assert left.passed and left.evidence == {"note": EXTRA_LEFT_OUT}
    shutil.rmtree(extra_run(root, "K2", "greedy"))
    chk = check(root, settings)
    assert chk.passed and chk.evidence["not_yet_run"] == ["results/extra/milan/K2/greedy/seed0/days.parquet"]


def test_without_the_workflows_list_the_extra_runs_are_those_the_figures_draw(clean):
    """`python -m audits` gives no list: the extra runs are then derived from the settings, as the workflow derives
    them: do(s) and scaling runs on figures.dataset, the foresight grid's and the headroom map's; a fleet-size or
    intensity variant retrains a learner, a do(s) variant does not."""
    from dswm import settings as S

    root, settings = clean
    jobs = extra.extra_runs(AuditContext(root=root, settings=settings))
    assert len(jobs) == len({j[:4] for j in jobs}) > 0
    want = {(settings.figures.dataset, v, m, s) for v, m, s in S.extra_jobs(settings)}
    want |= set(S.foresight_jobs(settings)) | set(S.headroom_jobs(settings))
    assert {j[:4] for j in jobs} == want
    retrains = {(v, m): r for _, v, m, _, r in jobs}
    assert any(v.startswith("do") for v, _ in retrains) and any(v.startswith("K") for v, _ in retrains)
    for (v, m), r in retrains.items():
        if not settings.methods[m].learns or v.startswith(("do", "rho", "alg")):
            assert r is False, (v, m)
        elif v.startswith(("K", "u")):
            assert r is True, (v, m)
    bare = dataclasses.replace(settings, figures=None)  # the workflow's audit slice: the rule must pass the list
    with pytest.raises(Exception, match="no figures section and no list of extra runs"):
        extra.extra_runs(AuditContext(root=root, settings=bare))
