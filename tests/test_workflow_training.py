"""The training part of the DAG (dry runs of the demo profile): one train job per training source and seed."""
from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

from dswm import settings as runconfig
from dswm.config import load_yaml
from conftest import LEARNING_BASELINES

ROOT = Path(__file__).resolve().parents[1]


def dry_run(*targets: str) -> subprocess.CompletedProcess:
    return subprocess.run([str(Path(sys.executable).parent / "snakemake"), "-n", "--forceall", "--nolock",
                           "--cores", "2", *targets, "--config", "profile=demo"], cwd=ROOT, capture_output=True,
                          text=True, timeout=120)


def test_methods_that_share_a_training_get_no_train_job_and_evaluate_the_source_model():
    resolved = runconfig.resolve({**load_yaml(ROOT / "config.yaml"), "profile": "demo"})
    sources = resolved.training_sources()
    assert sources["dswm_wo_unc"] == "dswm" and sources["dswm_wo_dec"] == "dswm_wo_dec"
    out = dry_run("tables")
    assert out.returncode == 0, out.stdout + out.stderr
    text = out.stdout + out.stderr
    seeds = [(ds, s) for ds in resolved.run.datasets for s in resolved.seeds(ds)]
    trained = sorted(re.findall(r"^rule train:\n(?:\s+.*\n)*?\s+output: results/(\w+)/(\w+)/seed(\d+)/model\.pt",
                                text, flags=re.M))
    own = [m for m in resolved.trained()]  # dswm, dswm_wo_dec and each learning baseline on its datasets
    assert sorted(own) == sorted(["dswm", "dswm_wo_dec", *[m for m in resolved.methods if m in LEARNING_BASELINES]])
    assert trained == sorted((ds, m, str(s)) for ds, m, s in resolved.jobs() if m in own)
    evaluated = re.findall(r"^rule evaluate:\n\s+input: ([^\n]*)\n\s+output: results/(\w+)/dswm_wo_unc/seed(\d+)/",
                           text, flags=re.M)
    assert sorted((ds, int(s)) for _, ds, s in evaluated) == sorted(seeds)
    for inputs, ds, s in evaluated:
        assert inputs.split(", ")[:2] == [f"results/{ds}/dswm/seed{s}/model.pt",
                                          f"results/{ds}/dswm/seed{s}/train_manifest.json"]
    counts = dict(re.findall(r"^(train|evaluate)\s+(\d+)$", text, flags=re.M))
    assert counts == {"train": str(len(trained)), "evaluate": str(len(resolved.jobs()))}
    # methods.only_on: JTORATC is evaluated on Milan's seeds only, INS-WOA on every dataset's
    for method, datasets in (("jtoratc", ["milan"]), ("ins_woa", list(resolved.run.datasets))):
        ran = re.findall(rf"^rule evaluate:\n(?:\s+.*\n)*?\s+output: results/(\w+)/{method}/seed(\d+)/days\.parquet",
                         text, flags=re.M)
        assert sorted(ran) == sorted((ds, str(s)) for ds, s in seeds if ds in datasets), method


def test_the_model_of_a_method_that_shares_a_training_cannot_be_requested():
    out = dry_run("results/milan/dswm_wo_unc/seed0/model.pt")
    assert out.returncode != 0
    assert "No rule to produce results/milan/dswm_wo_unc/seed0/model.pt" in out.stdout + out.stderr
    assert dry_run("results/milan/dswm_wo_dec/seed0/model.pt").returncode == 0
