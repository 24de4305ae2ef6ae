"""Where and how a job logs to MLflow is no rerun trigger: a change of any key under `mlflow:` but the experiment's
name leaves the params Snakemake compares unchanged for every job of `tables` and `figures` (so a finished tree
reruns nothing); the settings reach the jobs as the Untracked `params.tracking` (docs/PIPELINE.md)."""
from __future__ import annotations

import json
import subprocess
import sys
from collections import Counter
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
TARGETS = ("tables", "figures")


def tracked(*configfiles: Path) -> dict[str, list]:
    """{"<rule> <first output>": the params Snakemake records and compares} of every job of TARGETS (smoke)."""
    argv = [sys.executable, str(ROOT / "tests" / "dag_params.py"), str(ROOT), *TARGETS, "--config", "profile=smoke"]
    for f in configfiles:
        argv += ["--configfile", str(f)]
    proc = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return json.loads(proc.stdout)


@pytest.fixture(scope="module")
def default():
    return tracked()


def changed_by(default: dict, tmp_path: Path, mlflow: dict) -> Counter:
    """{rule: how many of its jobs a --configfile setting ``mlflow`` would rerun} (those whose params differ)."""
    path = tmp_path / "mlflow.yaml"
    path.write_text(yaml.safe_dump({"mlflow": mlflow}))
    now = tracked(path)
    assert now.keys() == default.keys()  # the same jobs
    return Counter(key.split()[0] for key in default if now[key] != default[key])


def smoke():
    from dswm import settings as S
    from dswm.config import load_yaml

    return S.resolve({**load_yaml(ROOT / "config.yaml"), "profile": "smoke"})


def test_the_jobs_of_tables_and_figures_are_the_expected_ones(default):
    s = smoke()
    rules = Counter(key.split()[0] for key in default)
    assert rules["evaluate"] == len(s.jobs()) and rules["mlflow_init"] == 1
    assert rules["train"] == len([j for j in s.jobs() if j[1] in s.trained()])
    assert rules["extra_evaluate"] > 0 and rules["probe"] > 0
    # the foresight figure reads the world model's replay of each of its datasets (smoke: Milan alone): one job per
    # main (dataset, seed) of dswm there
    assert s.figures.foresight.datasets == ("milan",)
    assert rules["wm_quality"] == len([j for j in s.jobs() if j[1] == "dswm" and j[0] == "milan"]) == 1
    assert rules["figure_foresight"] == rules["figure_headroom"] == 1


@pytest.mark.parametrize("mlflow", [{"http": {"timeout_s": 61}}, {"http": {"max_retries": 3, "backoff_factor": 1}},
                                    {"batch_size": 999}, {"tracking_uri": "http://127.0.0.1:5999"},
                                    {"store": "results/other.db", "artifacts": "results/other_artifacts"},
                                    {"unlogged": "results/kept"}],
                         ids=["timeout", "retries", "batch_size", "tracking_uri", "store", "unlogged"])
def test_a_reporting_only_mlflow_setting_reruns_no_job(default, tmp_path, mlflow):
    assert changed_by(default, tmp_path, mlflow) == Counter()


def test_a_new_experiment_name_reruns_every_job_that_logs_a_run(default, tmp_path):
    rerun = changed_by(default, tmp_path, {"experiment": "other"})
    jobs = Counter(key.split()[0] for key in default)
    assert (rerun["train"], rerun["evaluate"], rerun["mlflow_init"]) == (jobs["train"], jobs["evaluate"], 1)
    assert {"prepare", "calibrate", "audit_report", "build_tables"}.isdisjoint(rerun)


def test_the_jobs_receive_the_whole_mlflow_section_untracked():
    from dswm import settings as S
    from dswm.config import load_yaml

    s = smoke()
    assert S.tracking(s).value == load_yaml(ROOT / "config.yaml")["mlflow"]
    for job in (S.train_slice(s, "dswm"), S.evaluate_slice(s, "greedy"), S.figures_slice(s), S.mlflow_slice(s)):
        assert job.get("mlflow", job) == {"experiment": "dswm"}
    assert S.audit_slice(s)["mlflow"] is None
