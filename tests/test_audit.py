"""Mutation tests of the leakage audit: a clean tree passes; each leak turns its own check red.

The clean tree (audit_fixtures.build_clean_tree) holds raw files in the published Milan and YJMob formats,
tensors prepared by the real `prep` functions, result files, a training manifest and a checkpoint. Each test
copies it, plants one leak the way a faulty pipeline would, and asserts that the check for that leak fails
with a message naming the file and the leak.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from pathlib import Path

import numpy as np
import polars as pl
import pytest

from audit_fixtures import (T0, clean, method_record, model_record,  # noqa: F401 (fixtures)
                            one_torch_thread, prepare, tree, write_results, write_training)
from audits import crop, derived, protocol, splits, statistics, training
from audits.__main__ import main
from audits.context import AuditContext
from dswm.settings import Settings




def run(root: Path, settings: Settings, check):
    return check(AuditContext(root=root, settings=settings))


def tree_hashes(root: Path) -> dict[str, tuple[str, int]]:
    return {str(p.relative_to(root)): (hashlib.sha256(p.read_bytes()).hexdigest(), p.stat().st_mtime_ns)
            for p in sorted(root.rglob("*")) if p.is_file()}


def milan_train_p99_from_raw(root: Path) -> float:
    """The 99th percentile of internet summed over country codes, training files only (parsed here)."""
    frames = []
    for p in sorted((root / "results/raw/milan/demo").glob("*2013-11-*.txt")):
        frames.append(pl.read_csv(p, separator="\t", has_header=False, new_columns=[
            "sq", "t", "cc", "a", "b", "c", "d", "internet"], schema_overrides={"internet": pl.Float64}))
    df = pl.concat(frames).group_by("sq", "t").agg(pl.col("internet").fill_null(0).sum())
    assert df.height == 4 * 144 * 25  # every square and slot of the 4 training days is present
    return float(np.percentile(df["internet"].to_numpy(), 99))


def test_clean_tree_passes_and_nothing_changes(clean, tmp_path):
    root, _ = clean
    before = tree_hashes(root)
    out = tmp_path / "report"
    assert main(["--root", str(root), "--config", "config.json", "--out", str(out)]) == 0
    assert tree_hashes(root) == before
    report = json.loads((out / "report.json").read_text())
    assert report["passed"] and all(c["passed"] for c in report["checks"])
    assert {c["family"] for c in report["checks"]} == {"splits", "statistics", "protocol", "read-only"}
    read = {f["path"] for f in report["read_only"]["files"]}
    assert {"results/data/milan/meta.json", "results/data/yjmob/demand.parquet",
            "results/raw/yjmob/demo/yjmob100k-dataset1.csv.gz", "results/milan/dswm/seed0/train_manifest.json",
            "config.json"} <= read
    assert report["read_only"]["changed"] == [] and report["read_only"]["write_attempts"] == []
    p99 = next(c for c in report["checks"] if c["id"] == "statistics.p99")["evidence"]["milan"]
    assert p99["train"] == pytest.approx(milan_train_p99_from_raw(root), rel=1e-9)
    assert p99["stored"] == pytest.approx(p99["train"], rel=1e-9) and p99["all_days"] > 1.2 * p99["train"]
    assert "# Leakage audit: PASS" in (out / "report.md").read_text()


def test_test_day_moved_into_training(tree):
    root, settings = tree
    meta_path = root / "results/data/milan/meta.json"
    meta = json.loads(meta_path.read_text())
    first_test = next(d for d in meta["days"] if d["split"] == "test")
    first_test["split"] = "train"
    meta_path.write_text(json.dumps(meta))
    chk = run(root, settings, splits.check_segments)
    assert not chk.passed
    assert any("results/data/milan/meta.json" in m and "2013-12-21" in m and "a test day moved into training" in m
               for m in chk.failures), chk.failures


def test_p99_computed_on_all_days(tree, monkeypatch):
    root, settings = tree
    import prep.stats

    real = prep.stats.percentile
    monkeypatch.setattr(prep.stats, "percentile", lambda v, idx, q: real(v, np.arange(v.shape[0]), q))
    prepare(settings, root, only="milan")
    chk = run(root, settings, statistics.check_p99)
    assert any("results/data/milan/meta.json" in m and "p99 computed on all days" in m for m in chk.failures), \
        chk.failures
    tensor = run(root, settings, statistics.check_tensor)
    assert any("results/data/milan/demand.parquet" in m and "p99 over all days" in m for m in tensor.failures)
    assert all("yjmob" not in m for m in chk.failures + tensor.failures)


def test_kappa_from_test_segment(tree, monkeypatch):
    root, settings = tree
    import prep.stats

    real = prep.stats.mean_of
    test_idx = np.arange(10, 16)  # YJMob days d10..d15 are the fixture's test segment
    monkeypatch.setattr(prep.stats, "mean_of", lambda v, idx: real(v, test_idx))
    prepare(settings, root, only="yjmob")
    chk = run(root, settings, statistics.check_kappa)
    assert any("results/data/yjmob/meta.json" in m and "kappa from the test segment" in m for m in chk.failures), \
        chk.failures
    assert all("milan" not in m.split(":")[0] for m in chk.failures)


def test_method_evaluated_on_other_days(tree):
    root, settings = tree
    labels = [d["label"] for d in json.loads((root / "results/data/milan/meta.json").read_text())["days"]]
    other = labels.index("2013-12-26")  # a test day that is neither an ID nor an OOD day
    write_results(settings, root, "milan", "greedy", 0, days_override={"id": [4, 5, other], "ood": [7, 8]})
    chk = run(root, settings, protocol.check_result_days)
    assert len(chk.failures) == 1
    msg = chk.failures[0]
    assert "results/milan/greedy/seed0/days.parquet" in msg and "greedy evaluated on other days" in msg
    assert "2013-12-26" in msg and "2013-12-23" in msg


def test_different_observation_spec_for_one_method(tree):
    root, settings = tree
    from dswm.sim.core import Grid, obs_spec_hash

    other = obs_spec_hash(Grid(rows=5, cols=5, cell_m=500.0), dataclasses.replace(settings.scenario, obs_window=4))
    write_results(settings, root, "yjmob", "greedy", 0, obs_hash=other)
    chk = run(root, settings, protocol.check_hashes)
    assert len(chk.failures) == 1
    msg = chk.failures[0]
    assert "results/yjmob/greedy/seed0/days.parquet" in msg and "a different observation spec" in msg
    assert other in msg


def test_replay_buffer_holds_a_test_day(tree):
    root, settings = tree
    write_training(root, "milan", "dswm", 0, days=[0, 1, 2, 3, 5, 1])  # index 5 = 2013-12-22, a test day
    chk = run(root, settings, training.check_training_days)
    assert len(chk.failures) == 1  # once for the train job, not once per method that evaluates its model
    msg = chk.failures[0]
    assert "results/milan/dswm/seed0/train_manifest.json" in msg and "holds a test day" in msg
    assert "2013-12-22" in msg
    assert chk.evidence["learning_jobs"]["milan/dswm_wo_unc/seed0"] == "results/milan/dswm/seed0/train_manifest.json"


def test_a_method_that_shares_a_training_is_verified_through_its_source_manifest(clean):
    root, settings = clean
    assert not (root / "results/milan/dswm_wo_unc/seed0/train_manifest.json").exists()
    days = run(root, settings, training.check_training_days)
    assert days.passed, days.failures
    assert days.evidence["learning_jobs"] == {f"{ds}/{m}/seed0": f"results/{ds}/dswm/seed0/train_manifest.json"
                                              for ds in ("milan", "yjmob") for m in ("dswm", "dswm_wo_unc")}
    assert days.evidence["yjmob/dswm/seed0"]["evaluated_by"] == ["dswm", "dswm_wo_unc"]
    ckpt = run(root, settings, training.check_checkpoints)
    assert ckpt.passed and sorted(ckpt.evidence) == ["milan/dswm/seed0", "yjmob/dswm/seed0"]
    models = run(root, settings, training.check_evaluated_models)
    assert models.passed, models.failures
    model = root / "results/milan/dswm/seed0/model.pt"
    assert models.evidence["milan/dswm_wo_unc/seed0"] == {
        "train_source": "dswm", "model": "results/milan/dswm/seed0/model.pt",
        "expected": sha(model), "loaded": sha(model), "found": sha(model)}


def test_evaluation_that_loaded_a_model_its_source_did_not_train(tree):
    root, settings = tree
    stray = root / "results/milan/dswm_wo_unc/seed0/model.pt"  # a model trained for dswm_wo_unc after all
    stray.write_bytes(b"fixture model dswm_wo_unc")
    rec = {"method": "dswm_wo_unc", "train_source": "dswm", "model": "results/milan/dswm_wo_unc/seed0/model.pt",
           "model_sha256": sha(stray), "train_manifest": "results/milan/dswm/seed0/train_manifest.json"}
    write_results(settings, root, "milan", "dswm_wo_unc", 0, record=rec)
    chk = run(root, settings, training.check_evaluated_models)
    want = sha(root / "results/milan/dswm/seed0/model.pt")
    where = "results/milan/dswm_wo_unc/seed0/days.parquet"
    assert chk.failures == [
        f"{where}: model = 'results/milan/dswm_wo_unc/seed0/model.pt', expected results/milan/dswm/seed0/model.pt, "
        f"the model dswm trained",
        f"{where}: the evaluation loaded results/milan/dswm_wo_unc/seed0/model.pt with SHA-256 {sha(stray)}, "
        f"expected {want} (model_sha256 of results/milan/dswm/seed0/train_manifest.json) — dswm_wo_unc was "
        f"evaluated with a model dswm did not train",
        f"results/milan/dswm_wo_unc/seed0/model.pt: SHA-256 is {sha(stray)}, expected {want} (model_sha256 of "
        f"results/milan/dswm/seed0/train_manifest.json, which {where} names) — not the model dswm trained"]


def test_a_truncated_source_model_names_the_command_that_rebuilds_it(tree):
    """The model file cut short after its evaluation, file time restored: the audit says how to recover."""
    root, settings = tree
    model = root / "results/milan/dswm/seed0/model.pt"
    want, times = sha(model), os.stat(model)
    model.write_bytes(model.read_bytes()[: model.stat().st_size // 2])
    os.utime(model, ns=(times.st_atime_ns, times.st_mtime_ns))
    chk = run(root, settings, training.check_evaluated_models)
    assert chk.failures == [
        f"results/milan/dswm/seed0/model.pt: SHA-256 is {sha(model)}, expected {want} (model_sha256 of "
        f"results/milan/dswm/seed0/train_manifest.json, which results/milan/{m}/seed0/days.parquet names) — not the "
        f"model dswm trained; re-run its train job: `rm results/milan/dswm/seed0/model.pt`, then the same snakemake "
        f"command again (or add `--forcerun results/milan/dswm/seed0/model.pt` to it)" for m in ("dswm", "dswm_wo_unc")]


def test_evaluation_record_naming_the_source_model_with_another_hash(tree):
    root, settings = tree
    other = hashlib.sha256(b"a model loaded before dswm's training ended").hexdigest()
    rec = {"method": "dswm_wo_unc", "train_source": "dswm", "model": "results/yjmob/dswm/seed0/model.pt",
           "model_sha256": other, "train_manifest": "results/yjmob/dswm/seed0/train_manifest.json"}
    write_results(settings, root, "yjmob", "dswm_wo_unc", 0, record=rec)
    chk = run(root, settings, training.check_evaluated_models)
    assert len(chk.failures) == 1
    msg = chk.failures[0]
    assert msg.startswith("results/yjmob/dswm_wo_unc/seed0/days.parquet: the evaluation loaded "
                          "results/yjmob/dswm/seed0/model.pt")
    assert f"SHA-256 {other}" in msg and f"expected {sha(root / 'results/yjmob/dswm/seed0/model.pt')}" in msg


def test_evaluation_that_claims_another_training_source(tree):
    root, settings = tree
    rec = dict(model_record(settings, root, "milan", "dswm_wo_unc", 0), train_source="dswm_wo_unc")
    write_results(settings, root, "milan", "dswm_wo_unc", 0, record=rec)
    chk = run(root, settings, training.check_evaluated_models)
    assert chk.failures == ["results/milan/dswm_wo_unc/seed0/days.parquet: train_source = 'dswm_wo_unc', expected "
                            "'dswm' (the training source config.yaml gives dswm_wo_unc)"]
    assert rec["model"] == "results/milan/dswm/seed0/model.pt"


def test_learning_result_without_a_model_record(tree):
    root, settings = tree
    path = root / "results/yjmob/dswm/seed0/days.parquet"
    pl.read_parquet(path).write_parquet(path)  # what the evaluate job wrote before it recorded the model
    os.utime(path, (T0 + 20, T0 + 20))
    chk = run(root, settings, training.check_evaluated_models)
    assert len(chk.failures) == 1
    assert chk.failures[0].startswith("results/yjmob/dswm/seed0/days.parquet: no dswm.evaluated_model record")
    assert "re-run the evaluate job of yjmob/dswm/seed0" in chk.failures[0]


def rewrite_records(path: Path, *, method_rec: dict | None) -> None:
    """Rewrites a result file with the same table and model record and ``method_rec`` as its method record (none
    when None, as an evaluate job wrote before it recorded the method), keeping the fixture's file time."""
    from dswm.protocol.evaluation import MODEL_RECORD_KEY, read_model_record, write_days

    days, model_rec = pl.read_parquet(path), read_model_record(path)
    if method_rec is None:
        days.write_parquet(path, metadata={MODEL_RECORD_KEY: json.dumps(model_rec, sort_keys=True)})
    else:
        write_days(days, path, model_rec, method_rec)
    os.utime(path, (T0 + 20, T0 + 20))


def searching_results(root: Path, settings: Settings) -> list[tuple[str, str]]:
    """(result file, method) of every result file of the tree whose method record names a BCD search, run order."""
    from dswm.protocol.evaluation import read_method_record

    return [(f"results/{ds}/{m}/seed0/days.parquet", m) for ds in settings.run.datasets for m in settings.methods
            if read_method_record(root / f"results/{ds}/{m}/seed0/days.parquet")["search"] is not None]


def test_every_bcd_search_of_the_clean_run_is_identical(clean):
    root, settings = clean
    chk = run(root, settings, protocol.check_bcd_search_identical)
    assert chk.passed, chk.failures
    assert chk.id == "protocol.bcd_search_identical"
    greedy = method_record(settings, "greedy")
    assert greedy["search"] is not None  # greedy is the BCD on the current map: it runs one
    assert chk.evidence["search"] == greedy["search"]
    ran = [m for _, m in searching_results(root, settings)]
    assert "greedy" in chk.evidence["methods"] and chk.evidence["methods"] == list(dict.fromkeys(ran))
    assert chk.evidence["files"] == len(ran) and "static" in chk.evidence["without_search"]


def test_one_result_file_that_ran_another_search(tree):
    root, settings = tree
    from dswm.protocol.evaluation import read_method_record

    where, method = searching_results(root, settings)[-1]  # the last one: a clean file is the reference
    path = root / where
    rec = read_method_record(path)
    sweeps = rec["search"]["sweeps"]
    rec["search"]["sweeps"] = sweeps + 1  # one more pass over the UAVs than every other BCD of the run
    rewrite_records(path, method_rec=rec)
    chk = run(root, settings, protocol.check_bcd_search_identical)
    assert not chk.passed
    assert all(m.startswith(f"{where}: {method} ") for m in chk.failures), chk.failures
    differs = [m for m in chk.failures if "ran the BCD search" in m]
    assert len(differs) == 1, chk.failures
    ref_where, ref_method = searching_results(root, settings)[0]
    assert f"but {ref_where} ({ref_method}) ran" in differs[0]  # both files and both methods named
    assert f"they differ in sweeps: {sweeps + 1} vs {sweeps};" in differs[0]  # and the key that differs
    assert any(f"the settings give {method}" in m and f"sweeps: {sweeps + 1} vs {sweeps}" in m
               for m in chk.failures), chk.failures
    assert [v["files"] for v in chk.evidence["variants"] if v["search"]["sweeps"] == sweeps + 1] == [[where]]


def test_result_file_without_a_method_record(tree):
    root, settings = tree
    path = root / "results/milan/static/seed0/days.parquet"
    rewrite_records(path, method_rec=None)
    chk = run(root, settings, protocol.check_bcd_search_identical)
    assert len(chk.failures) == 1
    assert chk.failures[0].startswith("results/milan/static/seed0/days.parquet: no dswm.method_settings record")
    assert "re-run the evaluate job of milan/static/seed0" in chk.failures[0]
    assert run(root, settings, training.check_evaluated_models).passed  # its model record is still there


def test_method_record_of_another_method(tree):
    root, settings = tree
    rewrite_records(root / "results/yjmob/static/seed0/days.parquet", method_rec=method_record(settings, "greedy"))
    chk = run(root, settings, protocol.check_bcd_search_identical)
    assert ("results/yjmob/static/seed0/days.parquet: dswm.method_settings records method 'greedy', but the file is "
            "the result of 'static' — the settings recorded are another method's") in chk.failures, chk.failures
    assert all(m.startswith("results/yjmob/static/seed0/days.parquet: ") for m in chk.failures)


def test_a_run_without_a_bcd_search_passes_and_says_so(clean):
    root, settings = clean
    ctx = AuditContext(root=root, settings=settings)
    ctx.methods = ["static"]  # a run of Static alone: no method searches
    chk = protocol.check_bcd_search_identical(ctx)
    assert chk.passed, chk.failures
    assert chk.evidence["search"] is None and chk.evidence["methods"] == []
    assert "no method of the run runs a BCD search" in chk.evidence["note"]


def test_sharing_method_evaluated_before_its_source_training_ended(tree):
    root, settings = tree
    early = hashlib.sha256(b"dswm's model before its training ended").hexdigest()
    rec = dict(model_record(settings, root, "milan", "dswm_wo_unc", 0), model_sha256=early)
    result = write_results(settings, root, "milan", "dswm_wo_unc", 0, record=rec)
    os.utime(result, (T0 + 2, T0 + 2))  # before dswm's manifest closed (T0 + 10)
    chk = run(root, settings, training.check_checkpoints)
    assert chk.failures == ["results/milan/dswm_wo_unc/seed0/days.parquet: written before its training manifest "
                            "results/milan/dswm/seed0/train_manifest.json closed — the evaluation did not use the "
                            "final checkpoint"]


def test_result_older_than_the_manifest_that_records_loading_the_final_model_passes(tree):
    """The time rule speaks only where content is unproven: a result that records loading the model of the
    manifest's model_sha256 evaluated the final model, whatever its file time (a copy without times)."""
    root, settings = tree
    result = root / "results/milan/dswm_wo_unc/seed0/days.parquet"
    os.utime(result, (T0 + 2, T0 + 2))  # before dswm's manifest closed (T0 + 10)
    chk = run(root, settings, training.check_checkpoints)
    assert chk.passed, chk.failures
    assert chk.evidence["milan/dswm/seed0"]["file_times_not_compared"] == [
        "results/milan/dswm_wo_unc/seed0/days.parquet"]


def test_checkpoint_written_after_training_ended(tree):
    root, settings = tree
    ckpt = root / "results/yjmob/dswm/seed0/train/checkpoint.pt"
    ckpt.write_bytes(b"rewritten during evaluation")
    os.utime(ckpt, (T0 + 15, T0 + 15))  # after the manifest (T0 + 10), before the results (T0 + 20)
    chk = run(root, settings, training.check_checkpoints)
    assert any("results/yjmob/dswm/seed0/train/checkpoint.pt" in m and "after" in m for m in chk.failures), chk.failures
    assert len([m for m in chk.failures if "milan" in m]) == 0


def sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def rewrite_keeping_time(path: Path, data: bytes) -> None:
    """Replaces a file's content and sets its modification time back to what it was."""
    st = path.stat()
    path.write_bytes(data)
    os.utime(path, ns=(st.st_atime_ns, st.st_mtime_ns))


def test_clean_checkpoints_are_proven_by_their_hashes(clean):
    root, settings = clean
    chk = run(root, settings, training.check_checkpoints)
    assert chk.passed, chk.failures
    run_dir = root / "results/milan/dswm/seed0"
    ev = chk.evidence["milan/dswm/seed0"]
    assert ev["checkpoint_sha256"] == {"recorded": sha(run_dir / "train/checkpoint.pt"),
                                       "found": sha(run_dir / "train/checkpoint.pt")}
    assert ev["model_sha256"]["found"] == ev["model_sha256"]["recorded"] == sha(run_dir / "model.pt")
    assert ev["data_files_read"] == {f"results/data/milan/{n}": {"recorded": sha(root / "results/data/milan" / n),
                                                                 "found": sha(root / "results/data/milan" / n)}
                                     for n in ("demand.parquet", "meta.json")}


@pytest.mark.parametrize("run_dir, rel, key, what", [
    ("results/yjmob/dswm/seed0", "train/checkpoint.pt", "checkpoint_sha256", "the checkpoint was"),
    ("results/milan/dswm/seed0", "model.pt", "model_sha256", "the model file was"),
])
def test_trained_file_rewritten_with_its_file_time_restored(tree, run_dir, rel, key, what):
    root, settings = tree
    path = root / run_dir / rel
    before, mtime = sha(path), path.stat().st_mtime
    rewrite_keeping_time(path, b"rewritten during evaluation")
    assert path.stat().st_mtime == mtime  # the file times alone no longer show the rewrite
    chk = run(root, settings, training.check_checkpoints)
    assert chk.failures == [
        f"{run_dir}/{rel}: SHA-256 is {sha(path)}, {run_dir}/train_manifest.json recorded {key} = {before} — "
        f"{what} rewritten after training ended"]


def test_training_input_changed_after_training(tree):
    root, settings = tree
    meta = root / "results/data/yjmob/meta.json"
    before = sha(meta)
    meta.write_text(json.dumps(json.loads(meta.read_text()), indent=4))  # same content, other bytes
    chk = run(root, settings, training.check_checkpoints)
    assert len(chk.failures) == 1
    msg = chk.failures[0]
    assert msg.startswith(f"results/data/yjmob/meta.json: SHA-256 is {sha(meta)}, "
                          f"results/yjmob/dswm/seed0/train_manifest.json recorded data_files_read")
    assert f"= {before} — a training input changed after training" in msg


@pytest.mark.parametrize("key", ["checkpoint_sha256", "data_files_read"])
def test_manifest_that_predates_hashing(tree, key):
    root, settings = tree
    path = root / "results/milan/dswm/seed0/train_manifest.json"
    man = json.loads(path.read_text())
    if key == "data_files_read":
        man[key] = []  # what the train job recorded before it hashed its inputs
    else:
        del man[key]
    path.write_text(json.dumps(man))
    os.utime(path, (T0 + 10, T0 + 10))
    chk = run(root, settings, training.check_checkpoints)
    assert len(chk.failures) == 1
    msg = chk.failures[0]
    assert msg.startswith("results/milan/dswm/seed0/train_manifest.json: ")
    assert "the manifest predates content hashing" in msg and "re-run the train job" in msg
    assert (f"no {key} recorded" if key == "checkpoint_sha256" else "data_files_read = []") in msg


def test_initial_positions_from_all_days(tree):
    root, settings = tree
    from dswm.sim.core import Grid, initial_positions
    from prep.tensor import load

    scenario = settings.scenario
    t = load(root / "results/data/milan")
    grid = Grid(rows=5, cols=5, cell_m=235.0)
    train = initial_positions(t.demand[t.train_days].mean(axis=(0, 1)), grid, 16, scenario.init.kmeans_seed)
    alld = initial_positions(t.demand.mean(axis=(0, 1)), grid, 16, scenario.init.kmeans_seed)
    assert np.abs(alld - train).max() > 50.0  # the fixture's test days move demand east
    write_results(settings, root, "milan", "static", 0, init_pos=alld)
    chk = run(root, settings, derived.check_initial_positions)
    assert any("results/milan/static/seed0/trajectory.npz:id_pos" in m and "ALL-DAYS" in m for m in chk.failures), \
        chk.failures


def test_calibration_record_with_test_days(tree):
    root, settings = tree
    rec_path = root / "results/calibration/demand_intensity.json"
    rec = json.loads(rec_path.read_text())
    rec["train_days"] = rec["train_days"] + ["2013-12-21"]
    rec_path.write_text(json.dumps(rec))
    chk = run(root, settings, derived.check_calibration)
    assert any("results/calibration/demand_intensity.json" in m and "non-training day(s) ['2013-12-21']" in m for m in chk.failures), chk.failures


def test_full_audit_exits_nonzero_and_names_the_leak(tree, tmp_path):
    root, settings = tree
    write_training(root, "yjmob", "dswm", 0, days=[0, 1, 12])
    out = tmp_path / "report"
    assert main(["--root", str(root), "--config", "config.json", "--out", str(out)]) == 1
    report = json.loads((out / "report.json").read_text())
    failed = [c["id"] for c in report["checks"] if not c["passed"]]
    assert failed == ["protocol.training_days"]
    md = (out / "report.md").read_text()
    assert "# Leakage audit: FAIL" in md and "results/yjmob/dswm/seed0/train_manifest.json" in md and "d12" in md


def test_intensity_calibrated_on_test_days(tree):
    root, settings = tree
    from dswm.protocol.calibration import static_score
    from prep.tensor import load

    t = load(root / "results/data/milan")
    test_score = static_score(t, settings.scenario, t.test_days)
    train_score = settings.calibration.target_served_ratio
    assert abs(test_score - train_score) > 0.02  # the fixture's busier test days are served less
    calibration = dataclasses.replace(settings.calibration, target_served_ratio=test_score)
    settings = dataclasses.replace(settings, calibration=calibration)  # u now reaches the target on TEST days
    chk = run(root, settings, derived.check_calibration)
    assert any("config.yaml: scenario.demand_intensity" in m and "u calibrated on test days" in m
               for m in chk.failures), chk.failures



def calibrating(settings: Settings) -> Settings:
    """The settings with `scenario.demand_intensity: calibrate` (u from the calibrate rule's record)."""
    return dataclasses.replace(settings, scenario=dataclasses.replace(settings.scenario, demand_intensity="calibrate"))


def test_with_calibrate_the_audit_expects_the_records_intensity(tree):
    """The fixture's record holds the u its results were computed with: expected hashes and the calibration
    check use that number; another number in the record fails both, and no advice to copy it."""
    from audits.hashes import expected_hashes

    root, settings = tree
    ctx = AuditContext(root=root, settings=calibrating(settings))
    assert ctx.scenario == settings.scenario
    assert expected_hashes(ctx, "milan")["scenario_hash"] == settings.scenario.hash()
    chk = run(root, calibrating(settings), derived.check_calibration)
    assert chk.passed, chk.failures
    assert chk.evidence["u_from"] == "the calibrate rule's record results/calibration/demand_intensity.json"
    assert run(root, calibrating(settings), protocol.check_hashes).passed
    rec_path = root / "results/calibration/demand_intensity.json"
    rec = json.loads(rec_path.read_text())
    rec_path.write_text(json.dumps({**rec, "demand_intensity": 2 * rec["demand_intensity"]}))
    chk = run(root, calibrating(settings), derived.check_calibration)
    [msg] = chk.failures
    assert msg.startswith(f"results/calibration/demand_intensity.json: demand_intensity = "
                          f"{2 * rec['demand_intensity']:g} gives Static a served ratio of ")
    assert msg.endswith("(the record does not reproduce its own calibration; run the calibrate rule again)")
    assert "copy" not in msg
    hashes = run(root, calibrating(settings), protocol.check_hashes)
    assert any("scenario_hash" in m and "different scenario constants" in m for m in hashes.failures), hashes.failures


@pytest.mark.parametrize("record, found", [
    ({"served_ratio": 0.74}, "missing key 'demand_intensity' (expected the positive u the calibrate rule writes; "
                             "run it again)"),
    ({"demand_intensity": -1.0}, "key 'demand_intensity' must be a positive number; found -1.0 (run the calibrate "
                                 "rule again)"),
])
def test_with_calibrate_a_bad_record_fails_the_audit_naming_the_file_and_key(tree, record, found):
    root, settings = tree
    (root / "results/calibration/demand_intensity.json").write_text(json.dumps(record))
    chk = run(root, calibrating(settings), derived.check_calibration)
    assert chk.failures == [f"results/calibration/demand_intensity.json: {found} (scenario.demand_intensity is "
                            f"'calibrate': the jobs took u from this record) — the calibration cannot be verified"]
    hashes = run(root, calibrating(settings), protocol.check_hashes)
    assert hashes.failures and all("results/calibration/demand_intensity.json: " + found in m
                                   for m in hashes.failures), hashes.failures


def test_crop_chosen_on_all_days(tree):
    root, settings = tree
    raw = pl.read_csv(root / "results/raw/yjmob/demo/yjmob100k-dataset1.csv.gz").filter(pl.col("x") != 999)
    counts = np.zeros((12, 12))
    np.add.at(counts, (raw["y"].to_numpy() - 1, raw["x"].to_numpy() - 1), 1)
    sums = {(r, c): counts[r:r + 5, c:c + 5].sum() for r in range(8) for c in range(8)}
    r_all, c_all = max(sums, key=lambda k: (sums[k], -k[0], -k[1]))  # densest 5x5 window over ALL days
    meta_path = root / "results/data/yjmob/meta.json"
    meta = json.loads(meta_path.read_text())
    assert (meta["crop"]["first_y"] - 1, meta["crop"]["first_x"] - 1) != (r_all, c_all)
    meta["crop"].update(first_x=c_all + 1, first_y=r_all + 1)
    meta_path.write_text(json.dumps(meta))
    chk = run(root, settings, crop.check_crop)
    assert len(chk.failures) == 1
    assert "results/data/yjmob/meta.json" in chk.failures[0] and "crop chosen with test-period records" in \
        chk.failures[0], chk.failures
