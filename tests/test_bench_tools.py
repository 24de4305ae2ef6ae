"""The benchmark tools: the paper projection's arithmetic on hand-made rates and jobs, the speed-up record of a
side-by-side run, and (integration) ``bench_learners.py --quick`` on the smoke run's Milan tensor."""
from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest

from conftest import ROOT

sys.path.insert(0, str(ROOT / "benchmarks"))

import bench_learners  # noqa: E402
import diagnose_emorl  # noqa: E402
import gemm_ceiling  # noqa: E402
import project_paper as pp  # noqa: E402
from dswm import settings as runconfig  # noqa: E402
from dswm.config import load_yaml  # noqa: E402

DRYRUN = """\
[Thu Nov 26 02:16:13 2026]
rule train:
    input: results/data/milan/demand.parquet
    output: results/milan/sac/seed0/model.pt
    log: logs/train/milan/sac/seed0.log
    jobid: 7
    benchmark: results/benchmarks/train/milan/sac/seed0.tsv
    reason: Forced execution
    wildcards: dataset=milan, method=sac, seed=0
    resources: tmpdir=/tmp, runtime=1440
Shell command: None

[Thu Nov 26 02:16:13 2026]
localrule tables:
    input: results/tables/milan_main.csv
    jobid: 0
    reason: Forced execution
    resources: tmpdir=/tmp
Shell command: None
Job stats:
job       count
------  -------
tables        1
train         1
total         2
"""


def spread(median, slow, fast):
    """A measured rate: its median, its slowest repeat (min) and its fastest (max)."""
    return {"median": median, "min": slow, "max": fast}


RATES = {
    "profile": "paper",
    "environment": {"current": {"batches": {"8": {"fleet_slots_per_second": spread(1000.0, 500.0, 2000.0)}}}},
    "learners": {
        "sac": {"current": {"train": {"transitions_per_second": spread(100.0, 50.0, 200.0)}}},
        "dswm_world_model": {"current": {"collect": {"transitions_per_second": spread(10000.0, 5000.0, 20000.0)},
                                         "gradient": {"gradient_steps_per_second": spread(10.0, 5.0, 20.0)}}},
        "tdmpc": {"current": {"play": {"transitions_per_second": spread(20.0, 10.0, 40.0)}}},
    },
    "planners": {"current": {"dswm": {"median_ms": 500.0, "min_ms": 400.0, "max_ms": 800.0},
                             "jtoratc_full_solve": {"median_ms": 1000.0, "min_ms": 900.0, "max_ms": 1500.0}}},
}
WORK = {"sac": {"environment.8": 8000, "train.transitions_per_second": 360000},
        "dswm_world_model": {"collect.transitions_per_second": 60000, "gradient.gradient_steps_per_second": 36000}}


def job(rule, dataset=None, method=None, seed=None):
    w = {k: v for k, v in (("dataset", dataset), ("method", method), ("seed", seed)) if v is not None}
    bench = None if method is None else f"results/benchmarks/{rule}/{dataset}/{method}/seed{seed}.tsv"
    return pp.Job(rule, w, bench)


def test_the_dry_run_is_read_into_jobs_with_their_wildcards_and_benchmark_files():
    jobs = pp.parse_dryrun(DRYRUN)
    assert jobs == [pp.Job("train", {"dataset": "milan", "method": "sac", "seed": "0"},
                           "results/benchmarks/train/milan/sac/seed0.tsv"),
                    pp.Job("tables", {}, None)]


def test_paper_test_days_per_evaluation_and_the_demo_runs_days():
    config = load_yaml(ROOT / "config.yaml")
    assert pp.eval_days(config) == {"milan": 7, "shanghai": 7, "yjmob": 7}
    assert pp.day_limit(config, "demo", "milan") == 3        # 2 of the 3 ID days, 1 of the 4 OOD days
    assert pp.day_limit(config, "paper", "yjmob") == 7


def test_projection_adds_each_jobs_work_over_its_measured_rate(tmp_path):
    bench = tmp_path / "benchmarks" / "evaluate" / "milan" / "greedy"
    bench.mkdir(parents=True)
    for seed, s in ((0, 30.0), (2, 50.0)):     # greedy's seed 1 did not run there: the median of the others
        (bench / f"seed{seed}.tsv").write_text(f"s\th:m:s\tmax_rss\n{s}\t0:00:30\t600.0\n")
    jobs = [job("train", "milan", "sac", 0), job("train", "milan", "dswm", 0), job("train", "milan", "dswm_wo_dec", 1),
            job("evaluate", "milan", "dswm_plus", 0), job("evaluate", "milan", "jtoratc", 0),
            job("evaluate", "milan", "tdmpc", 0), job("evaluate", "milan", "greedy", 1), job("prepare")]
    rows = pp.project(jobs, rates=RATES, work=WORK, days={"milan": 7},
                      measured=pp.measured_lookup(tmp_path / "benchmarks", scale={"milan": 7 / 3}), tdmpc_parallel=10)
    h = 3600.0
    # SAC: 8,000 random transitions at the environment's 1,000/s + 360,000 at its 100/s
    assert rows[("train", "sac")]["median"] == pytest.approx((8 + 3600) / h)
    assert rows[("train", "sac")]["max"] == pytest.approx((4 + 1800) / h)      # every rate at its fastest repeat
    assert rows[("train", "sac")]["min"] == pytest.approx((16 + 7200) / h)
    # two world models: 60,000 collected at 10,000/s + 36,000 steps at 10/s each
    assert rows[("train", "dswm")]["median"] == pytest.approx(3606 / h)
    assert rows[("train", "dswm_wo_dec")]["median"] == pytest.approx(3606 / h)
    assert rows[("evaluate", "dswm_plus")]["median"] == pytest.approx(7 * 143 * 0.5 / h)
    assert rows[("evaluate", "jtoratc")]["min"] == pytest.approx(7 * 143 * 1.5 / h)
    assert rows[("evaluate", "tdmpc")]["median"] == pytest.approx(143 * 10 / 20 / h)
    assert rows[("evaluate", "greedy")]["median"] == pytest.approx(40 * 7 / 3 / h)
    assert rows[("prepare", "")]["median"] == pytest.approx(pp.DEFAULT_S / h)
    assert rows[("evaluate", "greedy")]["how"] == {"benchmark file"}
    text = pp.report(rows, notes=["a note"])
    total = (3608 + 2 * 3606 + 500.5 + 1001 + 71.5 + 280 / 3 + 60) / h
    assert text.splitlines()[-1] == f"total: {total:.1f} core-hours" == "total: 3.5 core-hours"
    assert "a note" in text
    assert "train (all)" in text and "evaluate (all)" in text


def test_a_reused_evaluation_costs_what_the_measured_runs_reused_ones_cost(tmp_path):
    bench = tmp_path / "benchmarks" / "evaluate" / "milan" / "ceiling"
    bench.mkdir(parents=True)
    for seed, s in ((0, 400.0), (1, 6.0), (2, 8.0)):     # seeds 1 and 2 reused seed 0's evaluation there
        (bench / f"seed{seed}.tsv").write_text(f"s\th:m:s\tmax_rss\n{s}\t0:00:30\t600.0\n")
    reused = lambda ds, method, seed: seed > 0     # noqa: E731  (the dataset's first seed is 0 in both profiles)
    lookup = pp.measured_lookup(tmp_path / "benchmarks", scale={"milan": 7 / 3}, reused_paper=reused,
                                reused_measured=reused)
    # seed 0 evaluates: its own file, scaled to the paper's days; seed 4 reuses: the median of the reused ones
    # (not the median over all seeds, 8 s), unscaled
    assert lookup(job("evaluate", "milan", "ceiling", 0)) == (pytest.approx(400.0 * 7 / 3), "benchmark file")
    assert lookup(job("evaluate", "milan", "ceiling", 4)) == (7.0, "benchmark file (reused seed)")
    assert lookup(job("evaluate", "milan", "ceiling", 1)) == (6.0, "benchmark file (reused seed)")   # its own
    # a seed the paper profile evaluates but the measured run reused takes the runs that evaluated
    own = pp.measured_lookup(tmp_path / "benchmarks", scale={"milan": 7 / 3}, reused_paper=lambda *k: False,
                             reused_measured=reused)
    assert own(job("evaluate", "milan", "ceiling", 1)) == (pytest.approx(400.0 * 7 / 3), "benchmark file")
    # a dataset whose reused evaluations did not run there takes the other datasets' reused ones
    assert lookup(job("evaluate", "shanghai", "ceiling", 2)) == (7.0, "benchmark file (reused seed)")
    assert lookup(job("evaluate", "shanghai", "ceiling", 0)) is None    # nothing evaluated it there
    # without the two functions, as before: any seed's file, every job scaled
    plain = pp.measured_lookup(tmp_path / "benchmarks", scale={"milan": 7 / 3})
    assert plain(job("evaluate", "milan", "ceiling", 4)) == (pytest.approx(8.0 * 7 / 3), "benchmark file")


def test_the_figures_jobs_cost_their_work_days_and_snapshots(tmp_path):
    config = load_yaml(ROOT / "config.yaml")
    paper = runconfig.resolve({**config, "profile": "paper"})
    demo = runconfig.resolve({**config, "profile": "demo"})
    # the paper's extra runs plan every test day, the demo's the figures' 2 ID days or the map's and grid's 1
    assert pp.extra_days(config, paper)("milan", "D250u2") == 7 and pp.extra_days(config, paper)("milan", "K8") == 7
    assert pp.extra_days(config, demo)("milan", "D250u2") == 1 and pp.extra_days(config, demo)("milan", "u2") == 2
    root = tmp_path / "benchmarks"
    for rel, s in (("extra_evaluate/milan/u2/greedy/seed0.tsv", 20.0),
                   ("extra_evaluate/milan/K8/greedy/seed0.tsv", 40.0),
                   ("evaluate/milan/greedy/seed1.tsv", 5.0), ("probe/milan/ppo/seed0.tsv", 9.0)):
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_text(f"s\th:m:s\tmax_rss\n{s}\t0:00:30\t600.0\n")
    reused = lambda ds, method, seed: seed > 0     # noqa: E731
    main = pp.measured_lookup(root, scale={"milan": 7 / 3}, reused_paper=reused, reused_measured=reused)
    extra = pp.Extras(days=lambda ds, v: 7, probe_points=4,
                      measured=pp.extra_lookup(root, paper_days=lambda ds, v: 7, measured_days=lambda ds, v: 2,
                                               reused_paper=reused, reused_measured=reused, main=main))
    jobs = [job("extra_train", "milan", "dswm", 0), job("extra_evaluate", "milan", "perfect", 0),
            job("extra_evaluate", "milan", "greedy", 0), job("extra_evaluate", "milan", "greedy", 3),
            job("probe", "milan", "dswm", 0), job("probe", "milan", "tdmpc", 0), job("probe", "milan", "ppo", 0)]
    for j, variant in zip(jobs, ("u2", "D250", "u2", "u2", None, None, None)):
        if variant:
            j.wildcards["variant"] = variant
    rows = pp.project(jobs, rates=RATES, work=WORK, days={"milan": 7}, measured=main, tdmpc_parallel=10, extra=extra)
    h = 3600.0
    assert rows[("extra_train", "dswm")]["median"] == pytest.approx(3606 / h)     # as a main world-model training
    assert rows[("extra_evaluate", "perfect")]["median"] == pytest.approx(7 * 143 * 0.5 / h)
    # greedy at seed 0: its own variant's 20 s over 2 days, x 7 days; at seed 3 the reused main evaluation's 5 s
    assert rows[("extra_evaluate", "greedy")]["median"] == pytest.approx((70 + 5) / h)
    assert rows[("extra_evaluate", "greedy")]["how"] == {"benchmark file per day", "benchmark file (reused seed)"}
    assert rows[("probe", "dswm")]["median"] == pytest.approx(4 * 143 * 0.5 / h)   # 4 snapshots x one day of plans
    assert rows[("probe", "tdmpc")]["median"] == pytest.approx(4 * 143 / 20 / h)
    assert rows[("probe", "ppo")]["median"] == pytest.approx(9 / h)
    # a variant that did not run there takes the method's other variants on the dataset, per day
    other = extra.measured(pp.Job("extra_evaluate", {"dataset": "milan", "variant": "u0.5", "method": "greedy",
                                                     "seed": "0"}, None))
    assert other == (pytest.approx((20 + 40) / 2 / 2 * 7), "benchmark file per day")
    # without the figures' costing, an extra run of a planner is a measured file like any job (none here: default)
    plain = pp.project(jobs[1:2], rates=RATES, work=WORK, days={"milan": 7}, measured=main, tdmpc_parallel=10)
    assert plain[("extra_evaluate", "perfect")]["how"] == {"default"}


def test_a_later_rates_file_replaces_only_the_learners_it_measured():
    trees = {"trees": {"current": {"rev": "a" * 40}}, "machine": {"cpus": 2, "load_avg_1min": 0.5}}
    again = {"profile": "paper", **trees,
             "learners": {"tdmpc": {"current": {"play": {"transitions_per_second": spread(40.0, 30.0, 50.0)}}}}}
    merged, notes = pp.merge_rates([("all.json", {**RATES, **trees}), ("tdmpc.json", again)])
    assert pp.rate(merged, "tdmpc", "play.transitions_per_second", "median") == 40.0
    assert pp.rate(merged, "sac", "train.transitions_per_second", "median") == 100.0
    assert pp.plan_ms(merged, "dswm", "median") == 500.0
    assert notes[0].endswith("dswm_world_model, sac, tdmpc, environment, planners")
    assert notes[1].startswith("rates: tdmpc.json") and notes[1].endswith("): tdmpc")
    with pytest.raises(SystemExit, match="tdmpc.json: rates measured under profile 'demo'"):
        pp.merge_rates([("all.json", {**RATES, **trees}), ("tdmpc.json", {**again, "profile": "demo"})])


def test_a_side_by_side_run_records_each_learners_speedup_beside_its_goal():
    base = {"settings_hash": "a", "train": {"transitions_per_second": spread(10.0, 9.0, 11.0),
                                            "gradient_steps_per_second": spread(5.0, 4.0, 6.0)}}
    cur = {"settings_hash": "a", "train": {"transitions_per_second": spread(40.0, 30.0, 50.0),
                                           "gradient_steps_per_second": spread(12.5, 10.0, 14.0)}}
    sac = bench_learners.compare("sac", cur, base)
    assert sac["speedup"] == 2.5 and sac["goal_speedup"] == 3.0 and sac["goal_met"] is False
    assert sac["speedups"] == {"train.transitions_per_second": 4.0, "train.gradient_steps_per_second": 2.5}
    assert sac["same_settings"] is True
    ppo = bench_learners.compare("ppo", cur, {**base, "settings_hash": "b"})
    assert ppo["speedup"] == 4.0 and ppo["goal_speedup"] is None and ppo["goal_met"] is None
    assert ppo["same_settings"] is False
    alone = bench_learners.compare("maddpg", cur, None)
    assert "speedup" not in alone and alone["baseline"] is None
    failed = bench_learners.compare("sac", cur, {"error": "bench_learners: sac in /b failed (exit 1)"})
    assert "speedup" not in failed and failed["baseline"]["error"].startswith("bench_learners: sac in /b failed")
    assert failed["current"] is cur


def test_the_gemm_ceiling_counts_products_only_and_groups_units_as_the_benchmark_does():
    """A unit's GEMM seconds are the self time of the product and convolution operators (microseconds summed over
    repeated keys); repeats sum ``group`` units from ``head`` on; the ceiling is the baseline's repeat over them."""
    class Event:
        def __init__(self, key, us):
            self.key, self.self_cpu_time_total = key, us

    seconds, by_op = gemm_ceiling.gemm_seconds([Event("aten::mm", 30_000), Event("aten::addmm", 5_000),
                                                Event("aten::mm", 10_000), Event("aten::copy_", 20_000),
                                                Event("aten::convolution_backward", 4_000),
                                                Event("aten::linear", 1_000)])
    assert seconds == pytest.approx(0.049)
    assert by_op["aten::mm"] == pytest.approx(0.04) and by_op["aten::copy_"] == pytest.approx(0.02)
    per_unit = [None, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0]
    assert gemm_ceiling.repeats(per_unit, head=2, repeats_=3, group=2) == [5.0, 9.0, 13.0]
    with pytest.raises(RuntimeError, match="expected 6 profiled units from unit 0, found 5"):
        gemm_ceiling.repeats(per_unit, head=0, repeats_=3, group=2)
    row = gemm_ceiling.ceiling(baseline_s=6.0, current_s=2.5, gemm_s=1.5)
    assert row == {"speedup": 2.4, "ceiling": 4.0, "gemm_share": 0.6, "other_s_now": 1.0, "other_s_at_goal": 0.5}
    # a goal the products alone exceed: nothing is left for the rest
    assert gemm_ceiling.ceiling(baseline_s=3.0, current_s=1.5, gemm_s=1.2)["other_s_at_goal"] == pytest.approx(-0.2)


def test_the_emorl_diagnosis_counts_lowered_tasks_and_the_executed_members_training():
    """Two untrained policies (0, 1), their warm-up runs (2, 3), then three tasks (4 from 2, 5 from 4, 6 from 3);
    the archive holds 4 and 5 and executes 4, which has its warm-up and one task behind it."""
    def member(parent, sr):
        return {"parent": parent, "objectives": np.array([sr, -0.75, 0.9])}

    members = {0: member(None, 0.60), 1: member(None, 0.61), 2: member(0, 0.59), 3: member(1, 0.62),
               4: member(2, 0.63), 5: member(4, 0.62), 6: member(3, 0.59)}
    sr_only, mixed = np.array([1.0, 0.0, 0.0]), np.array([0.5, 0.5, 0.0])
    tasks = [(0, sr_only, np.array([-0.01, 0, 0])), (1, mixed, np.array([0.01, 0, 0])),
             (2, sr_only, np.array([0.04, 0, 0])), (4, mixed, np.array([-0.01, 0, 0])),
             (3, sr_only, np.array([-0.03, 0, 0]))]
    blob = {"members": members, "tasks": tasks, "archive": [4, 5], "num_timesteps": 50_000}
    out = diagnose_emorl.summarize(blob, warmup_rounds=8, task_rounds=4, transitions_per_round=572,
                                    rule="best_served_ratio")
    assert out["warmup_tasks"] == 2 and out["warmup_sr_deltas"] == [-0.01, 0.01]
    assert (out["later_tasks"], out["later_lowered"]) == (3, 2)
    assert out["later_sr_delta_mean"] == 0.0
    assert (out["served_ratio_alone_tasks"], out["served_ratio_alone_lowered"]) == (2, 1)
    assert out["untrained_sr"] == [0.6, 0.61]
    assert out["deepest_lineage_tasks"] == 3
    assert out["executed_member"] == 4 and out["executed_lineage"] == [4, 2, 0]
    assert (out["executed_rounds"], out["executed_transitions"]) == (12, 12 * 572)
    assert out["run_transitions"] == 50_000


@pytest.mark.integration
def test_quick_benchmark_on_the_smoke_tensor_writes_every_learner(smoke_tables, tmp_path):
    out = tmp_path / "learners.json"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT / "src"), str(ROOT)])}
    proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "bench_learners.py"), "--quick",
                           "--parallel", "2", "--profile", "smoke",
                           "--tensor", str(smoke_tables / "results" / "data" / "milan"),
                           "--out", str(out)], env=env, capture_output=True, text=True, timeout=1200)
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads(out.read_text())
    assert result["parallel"] == 2 and result["quick"] is True
    assert set(result["learners"]) == set(bench_learners.LEARNERS) == {
        "dswm_world_model", "ppo", "sac", "maddpg", "tdmpc", "ga_matr", "hrl_tpra", "emorl_tcto"}
    for name, entry in result["learners"].items():
        cur = entry["current"]
        assert cur["transitions_per_second"]["median"] > 0 and cur["gradient_steps_per_second"]["median"] > 0, name
        assert cur["threads"] == 1 and cur["subnormals_flushed"] is True, name   # as every job (init_process)
    assert result["learners"]["ppo"]["current"]["train"]["seconds_per_repeat"]["repeats"] == 5
    assert result["planners"]["current"]["dswm"]["decisions"] == 5
    assert set(result["environment"]["current"]["batches"]) == {"1", "2", "10"}   # the smoke learners' batches
