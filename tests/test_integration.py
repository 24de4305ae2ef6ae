"""The whole DAG on the `smoke` profile in a temporary copy of the repository, then its outputs checked.

One run (module fixture): `snakemake tables calibrate --config profile=smoke` builds the demo raw data of the
three datasets, prepares them, creates the MLflow store, calibrates u on the Milan training days (config.yaml
says `calibrate`: every job that reads u takes it from that record), trains dswm and dswm_wo_dec (dswm_wo_unc and
dswm_plus share dswm's training), evaluates every configured method on one ID and one OOD day per dataset, audits
the tree, and writes both tables. Then `snakemake figures`: the extra runs behind the figures (do(s) probe,
scaling sweeps, the sample-efficiency probe of the snapshots the train jobs took, the world-model replay), every
figure, and the audit again, now over the probe files.
"""
import csv
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import polars as pl
import pytest
from mlflow.tracking import MlflowClient

from conftest import LEARNING_BASELINES, ROOT
from smoke import snakemake
from dswm.config import load_yaml

pytestmark = pytest.mark.integration

DATASETS = ("milan", "shanghai", "yjmob")
BASELINES = ("static", "greedy", "oracle")
METHODS = tuple(load_yaml(ROOT / "config.yaml")["methods"]["run"])  # every configured method is tabulated


def methods_on(ds):
    """The methods the smoke profile evaluates on ``ds`` (``methods.only_on`` keeps some to the main dataset)."""
    from dswm import settings as runconfig

    return runconfig.resolve({**load_yaml(ROOT / "config.yaml"), "profile": "smoke"}).methods_on(ds)


PAIRS = sorted((d, m) for d in DATASETS for m in methods_on(d))  # (dataset, method) of every evaluate job
LEARNERS = tuple(LEARNING_BASELINES)  # the learning baselines, each its own training source
CONTRACT_COLUMNS = ["day", "label", "split", "sr_mean", "energy_kj_per_slot", "energy_efficiency", "jain",
                    "plan_ms_per_slot", "obs_spec_hash", "eval_days_hash", "scenario_hash", "seed", "method",
                    "dataset"]  # docs/ARCHITECTURE.md, "Results"


@pytest.fixture(scope="module")
def run(smoke_run):
    """The copy of the working tree where the smoke DAG has run (tables and calibrate, then figures)."""
    return smoke_run


def read_csv(path):
    with open(path) as fh:
        return list(csv.DictReader(fh))


def seed_score(work, ds, method, split):
    days = pl.read_parquet(work / "results" / ds / method / "seed0" / "days.parquet")
    return float(days.filter(pl.col("split") == split)["sr_mean"].mean())


def dry_run_jobs(work, *targets) -> dict[str, int]:
    """{rule: job count} that `snakemake -n <targets>` would run now in ``work`` ({} when nothing)."""
    proc = snakemake(work, *targets, "--cores", "2", "-n")
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    text = proc.stdout + proc.stderr
    if "Job stats" not in text:
        return {}
    table = text.split("Job stats", 1)[1].split("total", 1)[0]
    return {rule: int(n) for rule, n in re.findall(r"^(\w+)\s+(\d+)$", table, flags=re.M)}


def test_the_finished_tree_is_up_to_date_for_every_documented_target(run):
    """After `tables calibrate` then `figures room_fill` (first: later tests change the tree), each target runs its
    own check alone (a target without output runs on every call; `room_fill`, its figure's files alone, has nothing to
    do): the probe files `figures` wrote are no input of the tables' audit, so nothing of `tables` is redone, nor of
    `figures`, `room_fill` or `audit`."""
    for target in ("tables", "figures", "audit"):
        assert dry_run_jobs(run, target) == {target: 1}, target
    assert dry_run_jobs(run, "room_fill") == {}  # a target of its figure's files alone, no job of its own


def test_both_tables_have_every_method_and_dataset_with_numbers_from_the_result_files(run):
    from dswm.protocol.tables import MAIN_COLUMNS

    main = read_csv(run / "results" / "tables" / "milan_main.csv")
    assert list(main[0]) == MAIN_COLUMNS
    assert MAIN_COLUMNS[:7] == ["method", "class", "weekday_mean", "weekday_std", "holiday_mean", "holiday_std",
                                "n_seeds"]  # the served-ratio columns first, then energy, efficiency and Jain
    assert sorted(r["method"] for r in main) == sorted(METHODS)
    classes = [(r["method"], r["class"]) for r in main if r["method"] in BASELINES]
    assert classes == [("greedy", "model-free"), ("static", "deployment"), ("oracle", "upper bound")]
    for r in main:
        assert float(r["weekday_mean"]) == pytest.approx(seed_score(run, "milan", r["method"], "id"), abs=1e-9)
        assert float(r["holiday_mean"]) == pytest.approx(seed_score(run, "milan", r["method"], "ood"), abs=1e-9)
        assert (r["n_seeds"], float(r["weekday_std"])) == ("1", 0.0)
        days = pl.read_parquet(run / "results" / "milan" / r["method"] / "seed0" / "days.parquet")
        assert float(r["jain_holiday_mean"]) == pytest.approx(days.filter(pl.col("split") == "ood")["jain"].mean())
        energy = days.filter(pl.col("split") == "id")["energy_kj_per_slot"].mean()
        if r["method"] == "ceiling":  # a bound that flies no fleet has no energy: an empty cell, "--" in the table
            assert energy is None and r["energy_weekday_mean"] == ""
        else:
            assert float(r["energy_weekday_mean"]) == pytest.approx(energy)
    cross = read_csv(run / "results" / "tables" / "cross_dataset.csv")
    assert list(cross[0]) == ["method", "dataset", "weekday_mean", "weekday_std", "holiday_mean", "holiday_std",
                              "n_seeds"]
    assert sorted((r["dataset"], r["method"]) for r in cross) == PAIRS
    assert len(PAIRS) < len(DATASETS) * len(METHODS)  # jtoratc is a Milan-only row: "--" in the other columns
    text = (run / "results" / "tables" / "cross_dataset.md").read_text()
    assert re.search(r"^\| JTORATC \| \d\.\d{3}/\d\.\d{3} \| -- \| -- \|$", text, flags=re.M), text
    for r in cross:
        assert float(r["weekday_mean"]) == pytest.approx(seed_score(run, r["dataset"], r["method"], "id"), abs=1e-9)
    for name in ("milan_main", "cross_dataset"):
        for ext in ("md", "tex"):
            text = (run / "results" / "tables" / f"{name}.{ext}").read_text()
            assert "profile: smoke" in text and "Milan: demo" in text and "YJMob: demo" in text


def test_repositioning_pays_on_every_dataset_and_the_oracle_bounds_greedy(run):
    for ds in DATASETS:
        static, greedy, oracle = (seed_score(run, ds, m, "id") for m in BASELINES)
        assert greedy > static, ds
        assert oracle > greedy, ds
        assert seed_score(run, ds, "perfect", "id") > greedy, ds   # planning on the true future maps pays too


def test_every_bcd_of_the_run_ran_the_one_search_and_the_tables_give_the_room(run):
    from dswm.methods.search import configured_search
    from dswm.protocol.evaluation import read_method_record

    cfg = load_yaml(run / "config.yaml")
    search = configured_search(cfg, "smoke")[0]   # the profile's: its budget merged in
    searching = {"greedy", "oracle", "dswm_plus", "dswm_plus_persist", "perfect"}
    for ds in DATASETS:
        for m in methods_on(ds):
            rec = read_method_record(run / "results" / ds / m / "seed0" / "days.parquet")
            assert rec["method"] == m
            if m in searching:
                assert {k: rec["search"][k] for k in ("sweeps", "lattice", "refine")} == \
                    {k: search[k] for k in ("sweeps", "lattice", "refine")}, (ds, m)
                assert sorted(rec["search"]["bw_logits"]) == sorted(search["bw_logits"])
            else:
                assert rec["search"] is None, (ds, m)
    report = json.loads((run / "results" / "audit" / "report.json").read_text())
    chk = next(c for c in report["checks"] if c["id"] == "protocol.bcd_search_identical")
    assert chk["passed"] and sorted(chk["evidence"]["methods"]) == sorted(searching)
    room = read_csv(run / "results" / "tables" / "room.csv")
    ladder, fill = cfg["tables"]["room"]["ladder"], cfg["tables"]["room"]["fill"]
    assert sorted((r["dataset"], r["split"], r["method"]) for r in room) == \
        sorted((d, s, m) for d in DATASETS for s in ("weekday", "holiday") for m in ladder + fill)
    for r in room:
        split = "id" if r["split"] == "weekday" else "ood"
        assert float(r["room"]) == pytest.approx(seed_score(run, r["dataset"], "perfect", split)
                                                 - seed_score(run, r["dataset"], "greedy", split), abs=1e-9)
    assert "Room a forecast could fill, Greedy (BCD) -> Perfect forecast (clairvoyant)" in \
        (run / "results" / "tables" / "milan_main.md").read_text()


def test_the_ceiling_bounds_the_oracle_and_the_perfect_forecast_on_every_dataset_and_split(run):
    """The per-slot ceiling is the top of the ladder Static -> Greedy -> Oracle -> Perfect -> Ceiling on every dataset
    and split (up to 0.002, the bounds' search noise), room.csv and both tables carry it, it flies no fleet, and the
    audit knows it as a clairvoyant bound."""
    room = read_csv(run / "results" / "tables" / "room.csv")
    for ds in DATASETS:
        for split, word in (("id", "weekday"), ("ood", "holiday")):
            ceiling = seed_score(run, ds, "ceiling", split)
            assert ceiling >= seed_score(run, ds, "perfect", split) - 0.002, (ds, split)
            assert ceiling >= seed_score(run, ds, "oracle", split) - 0.002, (ds, split)
            rungs = [(r["method"], int(r["rung"]), float(r["method_mean"])) for r in room
                     if (r["dataset"], r["split"]) == (ds, word) and r["rung"] != ""]
            assert [m for m, _, _ in rungs] == ["static", "greedy", "oracle", "perfect", "ceiling"]
            assert [i for _, i, _ in rungs] == [0, 1, 2, 3, 4]
            assert rungs[-1][2] == pytest.approx(ceiling, abs=1e-9)
        days = pl.read_parquet(run / "results" / ds / "ceiling" / "seed0" / "days.parquet")
        assert days["energy_kj_per_slot"].null_count() == days.height  # a bound that flies no fleet
    for name in ("milan_main.md", "cross_dataset.md"):
        text = (run / "results" / "tables" / name).read_text()
        assert "Ceiling (clairvoyant)" in text
        assert ("Ladder of references and bounds, Static (K-means) -> Greedy (BCD) -> Oracle (clairvoyant) -> "
                "Perfect forecast (clairvoyant) -> Ceiling (clairvoyant): Milan Weekday") in text
    report = json.loads((run / "results" / "audit" / "report.json").read_text())
    chk = next(c for c in report["checks"] if c["id"] == "protocol.clairvoyant_bounds")
    assert chk["passed"] and sorted(chk["evidence"]["clairvoyant"]) == ["ceiling", "oracle", "perfect"]
    assert chk["evidence"]["clairvoyant"]["ceiling"]["places"] is True


def test_result_files_follow_the_contract(run):
    for ds in DATASETS:
        hashes = set()
        for m in methods_on(ds):
            d = run / "results" / ds / m / "seed0"
            days = pl.read_parquet(d / "days.parquet")
            assert days.columns[: len(CONTRACT_COLUMNS)] == CONTRACT_COLUMNS
            assert days["split"].to_list() == ["id", "ood"] and set(days["method"]) == {m}
            assert days["sr_mean"].is_between(0, 1).all()
            assert days["energy_kj_per_slot"].is_null().all() if m == "ceiling" else \
                (days["energy_kj_per_slot"] > 0).all()
            hashes.add(tuple(days.row(0, named=True)[h] for h in ("obs_spec_hash", "eval_days_hash", "scenario_hash")))
            traj = np.load(d / "trajectory.npz")
            assert traj["id_pos"].shape == (144, 16, 2) and traj["ood_pos"].shape == (144, 16, 2)
            assert int(traj["id_day"]) == days["day"][0] and int(traj["ood_day"]) == days["day"][1]
            assert not list(d.glob(".*tmp*"))  # no temp file left behind
        assert len(hashes) == 1, f"{ds}: methods saw different observation specs, days or scenarios"


def training_sources(work):
    from dswm import settings as runconfig

    return runconfig.resolve({**load_yaml(work / "config.yaml"), "profile": "smoke"}).training_sources()


def test_training_manifests_hash_what_training_read_and_wrote_and_the_audit_verifies_them(run):
    from prep.rawio import sha256_file

    sources = training_sources(run)
    trained = sorted(set(sources.values()))
    assert trained == sorted(["dswm", "dswm_wo_dec", *LEARNERS])  # dswm_wo_unc evaluates dswm's model
    for ds in DATASETS:
        assert not (run / "results" / ds / "dswm_wo_unc" / "seed0" / "model.pt").exists()
        for m in [m for m in trained if m in methods_on(ds)]:
            d = run / "results" / ds / m / "seed0"
            man = json.loads((d / "train_manifest.json").read_text())
            assert man["model"] == f"results/{ds}/{m}/seed0/model.pt"
            assert man["model_sha256"] == sha256_file(d / "model.pt")
            ckpt = Path(man["checkpoint"])
            assert ckpt.parent.as_posix() == f"results/{ds}/{m}/seed0/train" and ckpt.stem == "checkpoint"
            assert man["checkpoint_sha256"] == sha256_file(run / ckpt)
            assert man["n_transitions"] == man["transitions_per_day_episode"] * len(man["days"]) > 0
            assert man["data_files_read"] == [
                {"path": f"results/data/{ds}/{name}", "sha256": sha256_file(run / "results" / "data" / ds / name)}
                for name in ("demand.parquet", "meta.json")]
    report = json.loads((run / "results" / "audit" / "report.json").read_text())
    chk = next(c for c in report["checks"] if c["id"] == "protocol.checkpoints")
    assert chk["passed"] and sorted(chk["evidence"]) == sorted(f"{ds}/{m}/seed0" for ds, m in PAIRS if m in trained)


def test_each_learning_evaluation_recorded_its_source_model_and_the_audit_verifies_it(run):
    from dswm.protocol.evaluation import read_model_record
    from prep.rawio import sha256_file

    sources = training_sources(run)
    client, runs = evaluate_runs(run)
    tags = {(r.data.tags["dataset"], r.data.tags["method"]): r.data.tags for r in runs}
    for ds in DATASETS:
        for m in methods_on(ds):
            rec = read_model_record(run / "results" / ds / m / "seed0" / "days.parquet")
            if m not in sources:
                assert rec == {"method": m, "train_source": None, "model": None, "model_sha256": None,
                               "train_manifest": None}
                assert "train_source" not in tags[(ds, m)]
                continue
            src = run / "results" / ds / sources[m] / "seed0"
            manifest = json.loads((src / "train_manifest.json").read_text())
            where = f"results/{ds}/{sources[m]}/seed0"
            assert rec == {"method": m, "train_source": sources[m], "model": f"{where}/model.pt",
                           "model_sha256": manifest["model_sha256"], "train_manifest": f"{where}/train_manifest.json"}
            assert rec["model_sha256"] == sha256_file(src / "model.pt")
            assert (tags[(ds, m)]["train_source"], tags[(ds, m)]["model_sha256"]) == (sources[m], rec["model_sha256"])
        wo_unc = read_model_record(run / "results" / ds / "dswm_wo_unc" / "seed0" / "days.parquet")
        assert wo_unc["model_sha256"] == sha256_file(run / "results" / ds / "dswm" / "seed0" / "model.pt")
    train_runs = client.search_runs([runs[0].info.experiment_id], filter_string="tags.stage = 'train'")
    assert sorted((r.data.tags["dataset"], r.data.tags["method"]) for r in train_runs) == \
        sorted((d, m) for d, m in PAIRS if m in set(sources.values()))
    for r in train_runs:  # the train run names every method whose evaluation loads its model
        src = r.data.tags["method"]
        assert r.data.tags["evaluated_as"] == ",".join(m for m in sources if sources[m] == src)
    assert {r.data.tags["evaluated_as"] for r in train_runs} == {"dswm,dswm_wo_unc,dswm_plus", "dswm_wo_dec",
                                                                 *LEARNERS}
    for r in train_runs:  # every learning method's training curve is in MLflow
        curves = [k for k in r.data.metrics if k not in ("train/n_transitions", "train/steps")]
        assert curves and len(client.get_metric_history(r.info.run_id, curves[0])) > 1, r.data.tags["method"]
    report = json.loads((run / "results" / "audit" / "report.json").read_text())
    chk = next(c for c in report["checks"] if c["id"] == "protocol.evaluated_models")
    assert chk["passed"] and sorted(chk["evidence"]) == sorted(f"{ds}/{m}/seed0" for ds, m in PAIRS if m in sources)
    assert chk["evidence"]["milan/dswm_wo_unc/seed0"]["found"] == \
        sha256_file(run / "results" / "milan" / "dswm" / "seed0" / "model.pt")


def test_one_test_day_in_any_learning_method_s_training_record_turns_the_audit_red(run, tmp_path):
    """The audit's proof that no learning method saw a test day, on the manifests the smoke run's real training
    wrote: one test-day episode added to each method's record fails protocol.training_days, naming every one of
    those files (one audit run over all of them)."""
    sources = training_sources(run)
    meta = json.loads((run / "results" / "data" / "milan" / "meta.json").read_text())
    test_day = next(d for d in meta["days"] if d["split"] == "test")
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"}
    methods = sorted(set(sources.values()))
    assert len(methods) >= 2, methods
    originals = {}
    try:
        for method in methods:
            path = run / "results" / "milan" / method / "seed0" / "train_manifest.json"
            originals[path] = path.read_text()
            man = json.loads(originals[path])
            assert man["days"] and man["n_transitions"] == man["transitions_per_day_episode"] * len(man["days"])
            man["days"].append(test_day["index"])
            man["day_labels"].append(test_day["label"])
            man["n_transitions"] += man["transitions_per_day_episode"]
            path.write_text(json.dumps(man))
        out = tmp_path / "audit"
        proc = subprocess.run([sys.executable, "-m", "audits", "--root", str(run), "--config",
                               str(run / "config.yaml"), "--profile", "smoke", "--out", str(out)],
                              cwd=run, env=env, capture_output=True, text=True, timeout=600)
    finally:
        for path, text in originals.items():
            path.write_text(text)
    assert proc.returncode == 1, proc.stderr[-3000:]
    report = json.loads((out / "report.json").read_text())
    chk = next(c for c in report["checks"] if c["id"] == "protocol.training_days")
    assert not chk["passed"]
    for method in methods:
        assert any(f"results/milan/{method}/seed0/train_manifest.json" in m and test_day["label"] in m
                   and "holds a test day" in m for m in chk["failures"]), (method, chk["failures"])
    assert [c["id"] for c in report["checks"] if not c["passed"]] == ["protocol.training_days"]


def evaluate_runs(work):
    client = MlflowClient(tracking_uri="sqlite:///" + str(work / "results" / "mlflow.db"))
    exp = client.get_experiment_by_name(load_yaml(work / "config.yaml")["mlflow"]["experiment"])
    return client, client.search_runs([exp.experiment_id], filter_string="tags.stage = 'evaluate'")


def test_every_job_is_one_finished_mlflow_run_and_a_rerun_adds_no_duplicate(run):
    client, runs = evaluate_runs(run)
    assert sorted((r.data.tags["dataset"], r.data.tags["method"]) for r in runs) == PAIRS
    for r in runs:
        assert r.info.status == "FINISHED"
        assert (r.data.tags["seed"], r.data.tags["profile"]) == ("0", "smoke")
        assert len(r.data.tags["config_hash"]) == 12 and r.data.tags["git_commit"]
        assert r.data.params["eval_days.id"] == "1" and r.data.params["method.name"] == r.data.tags["method"]
        assert {"id/sr_mean", "ood/sr_mean", "day/sr_mean"} <= set(r.data.metrics)
        assert "days.parquet" in [a.path for a in client.list_artifacts(r.info.run_id)]
    # a controller's per-day stats (stat_ columns of days.parquet) are metrics of its run too
    stats = {r.data.tags["dataset"]: r.data.metrics for r in runs if r.data.tags["method"] == "jtoratc"}
    days = pl.read_parquet(run / "results" / "milan" / "jtoratc" / "seed0" / "days.parquet")
    assert list(stats) == ["milan"]
    # smoke's 120 ms budget per slot: a full solve exceeds it, so the degradation rule holds the plan between solves
    assert ((days["stat_solves"] + days["stat_held_slots"]) == 143).all() and (days["stat_over_budget_solves"] >= 1).all()
    assert (days["stat_degraded_slots"] >= days["stat_held_slots"]).all() and (days["stat_held_slots"] > 0).all()
    assert stats["milan"]["id/stat_solve_ms_median"] == pytest.approx(days["stat_solve_ms_median"][0])
    assert stats["milan"]["ood/stat_degraded_slots"] == days["stat_degraded_slots"][1]
    assert client.get_metric_history(next(r.info.run_id for r in runs if r.data.tags["method"] == "jtoratc"),
                                     "day/stat_solves")[0].value == days["stat_solves"][0]
    proc = snakemake(run, "--cores", "1", "--force", "results/yjmob/static/seed0/days.parquet")
    assert proc.returncode == 0, proc.stderr[-3000:]
    _, again = evaluate_runs(run)
    finished = [r for r in again if r.info.status == "FINISHED"]
    assert len(finished) == len(PAIRS)
    assert sum(r.data.tags["job_key"] == "evaluate/yjmob/static/seed0" for r in finished) == 1


def test_every_result_was_computed_with_the_intensity_the_calibrate_rule_wrote(run):
    import dataclasses

    from dswm.sim.scenario import DEMO_INTENSITY, Scenario

    report = json.loads((run / "results" / "calibration" / "demand_intensity.json").read_text())
    cfg = load_yaml(run / "config.yaml")
    assert report["dataset"] == "milan" and report["train_days"][0] == "2013-11-01" and len(report["train_days"]) == 10
    assert report["served_ratio"] == pytest.approx(cfg["calibration"]["target_served_ratio"],
                                                   abs=cfg["calibration"]["tolerance"])
    # config.yaml says `calibrate`: every job took u from the record, and hashed that number
    assert cfg["scenario"]["demand_intensity"] == "calibrate"
    used = dataclasses.replace(Scenario.from_dict(cfg["scenario"]), demand_intensity=report["demand_intensity"])
    for ds in DATASETS:
        for m in methods_on(ds):
            days = pl.read_parquet(run / "results" / ds / m / "seed0" / "days.parquet")
            assert set(days["scenario_hash"]) == {used.hash()}, (ds, m)
    assert DEMO_INTENSITY == pytest.approx(report["demand_intensity"], rel=5e-4)  # the stand-in of tests
    log = (run / "logs" / "calibrate.log").read_text()
    assert "calibrated demand_intensity" in log and "every job that reads u takes it from" in log


def scheduled(work) -> dict[str, int]:
    """{rule: job count} that a dry run of the smoke targets would run now, less the `tables` target's gate, which
    runs on every call ({} when nothing else is to be done)."""
    jobs = dry_run_jobs(work, "tables", "calibrate")
    assert jobs.pop("tables") == 1, jobs  # the gate on the tables in place: every call
    return jobs


def test_a_job_reruns_on_the_settings_it_reads_only(run):
    """Each rule's trigger is the slice of settings its job reads: display settings, key order and where runs are
    logged rerun nothing, a scenario constant reruns what depends on it and no data preparation (last: it rewrites
    config.yaml)."""
    import yaml

    assert snakemake(run, "tables", "calibrate", "--cores", "2").returncode == 0  # up to date after earlier tests
    original = (run / "config.yaml").read_text()
    cfg = yaml.safe_load(original)
    assert scheduled(run) == {}

    def reordered(node):
        return {k: reordered(node[k]) for k in reversed(list(node))} if isinstance(node, dict) else node

    try:
        slower = yaml.safe_load(original)
        slower["evaluation"]["progress_mininterval_s"] = cfg["evaluation"]["progress_mininterval_s"] * 7
        (run / "config.yaml").write_text(yaml.safe_dump(slower, sort_keys=False))
        assert scheduled(run) == {}
        (run / "config.yaml").write_text(yaml.safe_dump(reordered(cfg), sort_keys=False))
        assert list(yaml.safe_load((run / "config.yaml").read_text())) != list(cfg)
        assert scheduled(run) == {}
        # where and how runs are logged (server, batch size, HTTP retries) travels Untracked: nothing reruns
        elsewhere = yaml.safe_load(original)
        elsewhere["mlflow"].update(tracking_uri="http://127.0.0.1:9", batch_size=999)
        elsewhere["mlflow"]["http"]["timeout_s"] += 1
        (run / "config.yaml").write_text(yaml.safe_dump(elsewhere, sort_keys=False))
        assert scheduled(run) == {}
        higher = yaml.safe_load(original)
        higher["scenario"]["altitude_m"] = cfg["scenario"]["altitude_m"] + 20.0
        (run / "config.yaml").write_text(yaml.safe_dump(higher, sort_keys=False))
        jobs = scheduled(run)
        assert {"train", "evaluate", "audit_report", "build_tables"} <= set(jobs), jobs
        # calibrate reads the scenario too (all but the intensity it calibrates); nothing of the data is redone.
        # The probes that `figures` wrote read the scenario, but they are no input of the tables' audit: `figures`
        # reruns them, `tables` does not
        assert set(jobs) - {"train", "evaluate", "audit_report", "build_tables", "calibrate"} == set(), \
            jobs
        assert jobs["evaluate"] == len(PAIRS)
    finally:
        (run / "config.yaml").write_text(original)


FIGURES = ("main", "ood", "ablation", "sample_efficiency", "scaling", "training", "wm_quality", "cross_dataset",
           "qualitative_milan", "qualitative_shanghai", "qualitative_yjmob", "qualitative_trajectories", "eda")


def test_every_figure_is_written_with_its_data_caption_and_profile(run):
    fig = run / "results" / "figures"
    for name in FIGURES:
        assert (fig / f"{name}.png").read_bytes()[:4] == b"\x89PNG", name
        assert (fig / f"{name}.pdf").read_bytes()[:5] == b"%PDF-", name
        first = (fig / f"{name}.csv").read_text().splitlines()[0]
        assert first.startswith("# Paper ") and f"({name}" in first and first.endswith("(profile: smoke)"), first
    # the main figure draws the numbers of the per-day files: Greedy's weekday bar is its seed's ID mean
    main = pl.read_csv(fig / "main.csv", comment_prefix="#")
    greedy = main.filter((pl.col("method") == "greedy") & (pl.col("split") == "id"))
    assert greedy["sr_mean"].to_list() == [pytest.approx(seed_score(run, "milan", "greedy", "id"), abs=1e-12)]
    # the probe audit the figures target needs covers the probe files, and passed
    report = json.loads((run / "results" / "audit" / "probes.json").read_text())
    (chk,) = [c for c in report["checks"] if c["id"] == "protocol.probes_out_of_tables"]
    probes = sorted(p.relative_to(run).as_posix()
                    for p in (run / "results" / "probes" / "milan").glob("*/seed0/probe.parquet"))
    assert report["passed"] and chk["passed"] and report["scope"] == "probes"
    assert len(probes) >= 2 and chk["evidence"]["probe_files"] == probes
    # ... and the extra audit covers every extra run under results/extra/ the figures drew, and passed
    report = json.loads((run / "results" / "audit" / "extra.json").read_text())
    (chk,) = [c for c in report["checks"] if c["id"] == "protocol.extra_runs"]
    assert report["passed"] and chk["passed"] and report["scope"] == "extra" and "not_yet_run" not in chk["evidence"]
    drawn = sorted("/".join(p.parent.relative_to(run / "results" / "extra").parts)
                   for p in (run / "results" / "extra").glob("*/*/*/seed*/days.parquet")
                   if p.parts[-4] != "room_fill")  # room_fill's arms: its own target, not a figure of `figures`
    assert sorted(chk["evidence"]["runs"]) == drawn and len(drawn) >= 4
    retrained = [k for k, v in chk["evidence"]["runs"].items() if (v["model"] or {}).get("fitted_by") == "extra_train"]
    assert retrained and all(k.split("/")[1][0] in "Ku" for k in retrained)


def test_the_foresight_grid_and_the_headroom_map_draw_the_runs_and_the_main_evaluations_on_the_same_days(run):
    """Every cell of the foresight grid is a main evaluation or an extra run (rho0, alg1) on each of its datasets;
    the headroom map's own cell is the main evaluations' first ID day, the ceiling's value stands in every D_max
    column, and the CSV names exactly the cells whose room reaches min_room. The smoke budget draws each on one
    dataset (config.yaml figures.budgets.smoke): the grid on Milan, the map on Shanghai."""
    from dswm.settings import figures_settings

    figures = figures_settings(load_yaml(ROOT / "config.yaml"), "smoke")
    assert (figures.foresight.datasets, figures.headroom.datasets) == (("milan",), ("shanghai",))
    fig = run / "results" / "figures"
    for name in ("foresight", "headroom"):
        assert (fig / f"{name}.png").read_bytes()[:4] == b"\x89PNG", name
        first = (fig / f"{name}.csv").read_text().splitlines()[0]
        assert first.startswith(f"# {name.capitalize()} (no paper figure): ") and first.endswith("(profile: smoke)"), first
    grid = pl.read_csv(fig / "foresight.csv", comment_prefix="#").filter(pl.col("panel") == "a")
    assert set(grid["dataset"]) == {"milan"}
    for ds in figures.foresight.datasets:
        part = grid.filter((pl.col("dataset") == ds) & (pl.col("planner") != "reference"))
        assert part.group_by("status").len().sort("status").rows() == [("extra", 4), ("main", 4)], ds
        own = part.filter((pl.col("planner") == "plus") & (pl.col("source") == "model") & (pl.col("rho") == 0.95))
        assert own["sr_mean"].to_list() == [pytest.approx(seed_score(run, ds, "dswm_plus", "id"), abs=1e-12)]
        extra = part.filter(pl.col("variant") == "alg1")["method"].sort().to_list()
        assert extra == ["dswm_plus_persist", "perfect"]
    assert set(pl.read_csv(fig / "foresight.csv", comment_prefix="#").filter(pl.col("panel") == "b")["dataset"]) == {
        "milan"}                                            # the world model's RMSE of the grid's dataset
    table = pl.read_csv(fig / "headroom.csv", comment_prefix="#")
    assert table.height == 1 * 2 * 2                        # smoke: Shanghai x D_max {500, 1500} x u {1, 2}
    assert set(table["dataset"]) == {"shanghai"}
    for ds in figures.headroom.datasets:
        own = table.filter((pl.col("dataset") == ds) & (pl.col("d_max_m") == 1500.0) & (pl.col("factor") == 1.0))
        assert own["greedy"].to_list() == [pytest.approx(seed_score(run, ds, "greedy", "id"), abs=1e-12)]
        assert own["ceiling"].to_list() == [pytest.approx(seed_score(run, ds, "ceiling", "id"), abs=1e-12)]
        heavy = table.filter((pl.col("dataset") == ds) & (pl.col("factor") == 2.0))
        assert heavy["ceiling"].n_unique() == 1            # no motion limit: one run serves every D_max
    room = table["perfect"] - table["greedy"]
    assert table["named"].to_list() == (room >= 0.02).to_list()
    assert table.filter(pl.col("named"))["regime"].null_count() == 0


def test_room_fill_shares_the_room_of_greedy_and_perfect_on_the_same_days_and_fits_on_training_days_only(run):
    """Figure room_fill: every arm on the regime's test day (smoke: Shanghai, D_max 1500 m, u x 2, one ID day), the
    share (SR - Greedy) / (Perfect - Greedy) of each from the arms' own days.parquet; the candidate's rho_k (one per
    imagined step, in [0, 1]) and gamma chosen on the last training days, never a test day."""
    fig = run / "results" / "figures"
    assert (fig / "room_fill.png").read_bytes()[:4] == b"\x89PNG"
    first = (fig / "room_fill.csv").read_text().splitlines()[0]
    assert first.startswith("# Room fill (no paper figure): ") and first.endswith("(profile: smoke)"), first
    table = pl.read_csv(fig / "room_fill.csv", comment_prefix="#")
    arms = ["greedy", "perfect", "dswm", "dswm_plus", "dswm_plus_persist", "dswm_plus_rhok"]
    assert table.filter(pl.col("split") == "id")["arm"].to_list() == arms
    assert sorted(set(table["split"])) == ["all", "id"] and set(table["dataset"]) == {"shanghai"}
    base = run / "results" / "extra" / "shanghai" / "room_fill"
    sr = {a: pl.read_parquet(base / a / "seed0" / "days.parquet")["sr_mean"].mean() for a in arms}
    row = {r["arm"]: r for r in table.filter(pl.col("split") == "id").iter_rows(named=True)}
    room = sr["perfect"] - sr["greedy"]
    for a in arms:
        assert row[a]["sr"] == pytest.approx(sr[a], abs=1e-12) and row[a]["room"] == pytest.approx(room, abs=1e-12)
        assert row[a]["share"] == (pytest.approx((sr[a] - sr["greedy"]) / room, abs=1e-9) if room > 0 else None)
    fit = json.loads((base / "fit" / "seed0.json").read_text())
    meta = json.loads((run / "results" / "data" / "shanghai" / "meta.json").read_text())
    train = [d["label"] for d in meta["days"] if d["split"] == "train"]
    assert fit["validation_days"] == train[-1:] and fit["fit_days"] == train[-2:-1] and not fit["read_test_data"]
    assert len(fit["rho_steps"]) == load_yaml(run / "config.yaml")["dswm"]["planner"]["horizon"]
    assert all(0.0 <= r <= 1.0 for r in fit["rho_steps"]) and fit["gamma"] in (0.5, 0.9)


def test_the_mlflow_experiment_opens_on_runs_and_each_evaluation_records_its_demand_tensor(run):
    from prep.rawio import sha256_file

    client, runs = evaluate_runs(run)
    exp = client.get_experiment_by_name(load_yaml(run / "config.yaml")["mlflow"]["experiment"])
    assert exp.tags["mlflow.experimentKind"] == "custom_model_development"
    digests = {d: sha256_file(run / "results" / "data" / d / "demand.parquet")[:16] for d in DATASETS}
    for r in runs:
        (entry,) = r.inputs.dataset_inputs
        assert (entry.dataset.name, entry.dataset.digest) == (r.data.tags["dataset"], digests[r.data.tags["dataset"]])
    dswm = next(r for r in runs if (r.data.tags["dataset"], r.data.tags["method"]) == ("milan", "dswm"))
    logged = {a.path for a in client.list_artifacts(dswm.info.run_id, "figures")}
    assert {"figures/main.png", "figures/ood.png", "figures/ablation.png", "figures/wm_quality.png",
            "figures/foresight.png"} <= logged
    greedy = next(r for r in runs if (r.data.tags["dataset"], r.data.tags["method"]) == ("shanghai", "greedy"))
    assert "figures/headroom.png" in {a.path for a in client.list_artifacts(greedy.info.run_id, "figures")}
    # the experiment holds the tables' runs alone (kind main); the figures' runs are in <experiment>-figures
    main = client.search_runs([exp.experiment_id], max_results=1000)
    assert {(r.data.tags["kind"], r.data.tags["stage"]) for r in main} == {("main", "train"), ("main", "evaluate")}
    figures = client.get_experiment_by_name(exp.name + "-figures")
    kinds = {r.data.tags["kind"] for r in client.search_runs([figures.experiment_id], max_results=1000)}
    assert kinds == {"extra", "probe", "wm_quality"}


def test_a_probe_number_copied_into_a_table_source_turns_the_audit_red(run, tmp_path):
    """The audit's proof that probe numbers stay out of the tables, on the smoke run's real probe files: a
    checkpoint's probe value copied into the method's days.parquet, its content record re-written so that the record
    check cannot see it, fails protocol.probes_out_of_tables, naming that file (the rewritten file also loses the
    metadata the model and search checks read)."""
    from dswm.protocol.evaluation import write_eval_record

    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"}
    found = None
    for path in sorted((run / "results" / "probes" / "milan").glob("*/seed0/probe.parquet")):
        probe = pl.read_parquet(path)
        own = probe.filter(pl.col("sr_mean") != pl.col("evaluated_sr_mean"))
        if own.height:
            found = path.parent.parent.name, own.row(0, named=True)
            break
    assert found is not None, "no probe value differs from its evaluation's"
    method, row = found
    result = run / "results" / "milan" / method / "seed0"
    days_path, record = result / "days.parquet", result / "eval_manifest.json"
    originals = {p: p.read_bytes() for p in (days_path, record)}
    import pyarrow as pa
    import pyarrow.parquet as pq

    table = pq.read_table(days_path)  # keeps the file's schema and metadata: only one value changes
    i = table.schema.get_field_index("sr_mean")
    values = [row["sr_mean"] if d == row["day"] else v
              for d, v in zip(table["day"].to_pylist(), table["sr_mean"].to_pylist())]
    assert values != table["sr_mean"].to_pylist()
    try:
        pq.write_table(table.set_column(i, table.schema.field(i), pa.array(values, table.schema.field(i).type)),
                       days_path)
        write_eval_record(record, {"days.parquet": days_path, "trajectory.npz": result / "trajectory.npz"})
        out = tmp_path / "audit"
        proc = subprocess.run([sys.executable, "-m", "audits", "--root", str(run), "--config", str(run / "config.yaml"),
                               "--profile", "smoke", "--out", str(out)], cwd=run, env=env, capture_output=True,
                              text=True, timeout=600)
    finally:
        for p, data in originals.items():
            p.write_bytes(data)
    assert proc.returncode == 1
    report = json.loads((out / "report.json").read_text())
    assert "protocol.probes_out_of_tables" in [c["id"] for c in report["checks"] if not c["passed"]]
    chk = next(c for c in report["checks"] if c["id"] == "protocol.probes_out_of_tables")
    assert any(f"results/milan/{method}/seed0/days.parquet" in m for m in chk["failures"]), chk["failures"]
