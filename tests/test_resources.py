"""What each job asks a cluster scheduler for (config.yaml `resources`, workflow/rules/common.smk job_resources):
per rule and budget profile, and one GPU for a torch job whose device is cuda (docs/CLUSTER.md)."""
from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

from conftest import dry_run_blocks
from dswm import settings as runconfig
from dswm.config import load_yaml

ROOT = Path(__file__).resolve().parents[1]


def job_resources(text: str) -> dict[tuple[str, str], dict[str, str]]:
    """{(rule, first output): {resource: value}} of every job a dry run printed."""
    jobs = {}
    for key, block in dry_run_blocks(text).items():
        res = re.search(r"^\s+resources: (.+)$", block, flags=re.M)
        if res:
            jobs[key] = dict(kv.split("=", 1) for kv in res.group(1).split(", "))
    return jobs


def dry_run(*config: str) -> dict[tuple[str, str], dict[str, str]]:
    targets = ["results/milan/dswm/seed0/days.parquet", "results/milan/greedy/seed0/days.parquet"]
    proc = subprocess.run([str(Path(sys.executable).parent / "snakemake"), "-n", "--forceall", "--nolock",
                           "--cores", "2", *targets, "--config", "profile=smoke", *config], cwd=ROOT,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return job_resources(proc.stdout + proc.stderr)


def test_each_rule_asks_for_its_budgets_memory_and_time_and_a_gpu_only_on_cuda():
    cfg = load_yaml(ROOT / "config.yaml")
    smoke = runconfig.resource_settings(cfg, "smoke")
    assert smoke.of("train").runtime == cfg["resources"]["budgets"]["smoke"]["rules"]["train"]["runtime"]
    assert smoke.of("train").mem_mb == cfg["resources"]["rules"]["train"]["mem_mb"]  # unchanged keys are kept
    assert smoke.of("no_such_rule") == runconfig.resource_settings(cfg, "smoke").default

    cpu = dry_run()
    train = cpu[("train", "results/milan/dswm/seed0/model.pt")]
    assert (train["mem_mb"], train["runtime"], train["gpu"]) == (str(smoke.of("train").mem_mb),
                                                                 str(smoke.of("train").runtime), "0")
    assert cpu[("prepare", "results/data/milan/demand.parquet")]["mem_mb"] == str(smoke.of("prepare").mem_mb)

    gpu = dry_run("dswm={device: cuda}", "resources={gpu_slurm_extra: '--constraint=a100'}")
    assert gpu[("train", "results/milan/dswm/seed0/model.pt")]["gpu"] == "1"
    assert gpu[("train", "results/milan/dswm/seed0/model.pt")]["slurm_extra"] == "--constraint=a100"
    assert gpu[("evaluate", "results/milan/dswm/seed0/days.parquet")]["gpu"] == "1"
    # Greedy runs on evaluation.device, still the CPU
    assert gpu[("evaluate", "results/milan/greedy/seed0/days.parquet")]["gpu"] == "0"
    assert gpu[("evaluate", "results/milan/greedy/seed0/days.parquet")].get("slurm_extra", "") == ""


def _priorities(*config: str) -> tuple[int, dict[str, str]]:
    """(return code, {rule and first output: priority}) of a smoke dry run of three main evaluations."""
    targets = [f"results/milan/{m}/seed0/days.parquet" for m in ("ceiling", "ga_matr", "greedy")]
    proc = subprocess.run([str(Path(sys.executable).parent / "snakemake"), "-n", "--forceall", "--nolock",
                           "--cores", "2", *targets, "--config", "profile=smoke", *config], cwd=ROOT,
                          capture_output=True, text=True, timeout=120)
    found = {}
    for (rule, out), block in dry_run_blocks(proc.stdout + proc.stderr).items():
        prio = re.search(r"^\s+priority: (\d+)$", block, flags=re.M)
        found[f"{rule} {out}"] = prio.group(1) if prio else "0"
    return proc.returncode, found if proc.returncode == 0 else {"error": proc.stdout + proc.stderr}


def test_the_methods_of_start_order_start_first_and_a_misspelled_one_is_named():
    assert load_yaml(ROOT / "config.yaml")["resources"]["start_order"] == ["ceiling", "ga_matr"]
    rc, found = _priorities()
    assert rc == 0, found
    assert found["evaluate results/milan/ceiling/seed0/days.parquet"] == "2"
    assert found["train results/milan/ga_matr/seed0/model.pt"] == "1"
    assert found["evaluate results/milan/ga_matr/seed0/days.parquet"] == "1"
    assert found["evaluate results/milan/greedy/seed0/days.parquet"] == "0"
    rc, found = _priorities("resources={start_order: [greedy]}")
    assert rc == 0 and found["evaluate results/milan/greedy/seed0/days.parquet"] == "1", found
    assert found["evaluate results/milan/ceiling/seed0/days.parquet"] == "0"
    rc, found = _priorities("resources={start_order: [celing]}")
    assert rc != 0
    assert "--config: key 'resources.start_order' names 'celing', which is no method" in found["error"]
