"""Projected core-hours of the paper profile, from measured rates and the DAG's job list.

Run: python benchmarks/project_paper.py [--rates benchmarks/results/learners_cpu_t1.json [--rates more.json]]
         [--target tables] [--after TARGET] [--measured results/benchmarks --measured-profile demo]
Prints one row per rule and method (jobs, core-hours at the median rates, and at the fastest and the slowest
repeat), a subtotal per rule, the assumptions, and last a line ``total: N core-hours``.

The job list is the DAG's: ``snakemake -n --forceall --config profile=paper <target>`` in the repository (every job,
with its rule, wildcards and benchmark file; ``--jobs FILE`` reads a saved dry-run output instead). A job's cost,
in seconds of one core:

* ``train``: its work at the paper budget (config.yaml under ``paper``, resolved by ``dswm.settings``) over the rate
  ``bench_learners.py`` measured for that work (its "current" side), summed (:func:`train_work`):
  - transitions of the training loop / its transitions per second (PPO, SAC, MADDPG, GA-MATR, HRL-TPRA, EMORL-TCTO;
    EMORL-TCTO's count includes its policies' measurement days, as its manifest does);
  - uniform random transitions before learning (SAC's learning_starts, MADDPG's warmup) / the environment's rate at
    that batch (``environment``: the ceiling, no learner work in them);
  - pre-collected transitions / the pre-collection rate, gradient steps / gradient steps per second (DSWM's world
    model: dswm and dswm_wo_dec train one each; TD-MPC's seed phase);
  - TD-MPC's own transitions / its MPPI episodes' rate, plus their gradient steps (one per transition) at its rate.
* ``evaluate``: DSWM's planners (dswm, its ablations, DSWM+, its probe, the perfect forecast): test days x 143
  decisions x DSWM's plan ms per decision (Algorithm 1 at the paper's N/I/H/K; DSWM+'s proposal and warm start are
  not timed apart); JTORATC: the same decisions x its full-solve ms (at the paper's 8 s budget every slot is a full
  solve); TD-MPC: 143 slots x the time of one MPPI step of its ``parallel`` training days (the evaluated days, at
  most that many, are planned as one batch).
* everything else (the other evaluations, prepare, calibrate, eda, audit, tables): the seconds (``s``) of the same
  job's benchmark file in ``--measured`` (a finished run's ``results/benchmarks``; another seed's when that seed did
  not run there), evaluations scaled by the paper's test days over the days that run evaluated
  (``--measured-profile``); a job with no measured file counts :data:`DEFAULT_S` seconds. An evaluation that
  reuses another seed's (``evaluation.reuse_seed_independent``: a method the seed does not change, at any seed but
  the dataset's first) costs what the measured run's reused evaluations cost, unscaled.
* the figures' jobs (``--target figures``; ``--after tables`` leaves out the jobs that ``tables`` runs):
  ``extra_train`` as the main train job of its method; ``extra_evaluate`` of a planner: the run's test days
  (``dswm.settings.variant_days``) x 143 x DSWM's plan ms, of another method: the measured extra runs of that method
  on that dataset (the same variant's, else any variant's) in seconds per day they evaluated, x the run's days (a
  reuse as a reused main evaluation); ``probe`` of a planner: ``figures.sample_efficiency.fractions`` snapshots x
  one day (143 decisions) x DSWM's plan ms (TD-MPC's: x its MPPI step of one day), of another method its measured
  file; ``wm_quality`` and the figure rules their measured files.

One job holds one core (as the workflow runs them); core-hours are the sum over jobs. The rates are one machine's
(its load is in the rates file); the range is that of the rates' repeats, not of the machine.
"""
from __future__ import annotations

import argparse
import json
import re
import statistics
import subprocess
import sys
from collections import defaultdict
from pathlib import Path
from typing import Callable, Iterable, Mapping, NamedTuple, Sequence

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
DAY = 143
"""Decisions (transitions) per day-episode."""
DEFAULT_S = 60.0
"""Seconds counted for a job without a measured benchmark file (readers and writers of result files)."""
PLANNERS = ("dswm", "dswm_wo_unc", "dswm_wo_dec", "dswm_plus", "dswm_plus_persist", "perfect")
"""Evaluations whose cost is DSWM's plan per decision."""
WORLD_MODELS = ("dswm", "dswm_wo_dec")
"""Train jobs of DSWM's world model."""
CASES = ("median", "max", "min")
"""Which rate of each measurement: the median, the fastest repeat (least core-hours) and the slowest (most)."""


class Job(NamedTuple):
    rule: str
    wildcards: dict
    benchmark: str | None


# ---- the job list ------------------------------------------------------------------------------------------
def parse_dryrun(text: str) -> list[Job]:
    """The jobs of a ``snakemake -n`` output: rule, wildcards and benchmark file of every job block."""
    jobs, rule, wildcards, bench = [], None, {}, None
    for line in text.splitlines():
        m = re.match(r"^(?:local)?rule (\w+):$", line.strip()) if not line.startswith("    ") else None
        if m:
            if rule is not None:
                jobs.append(Job(rule, wildcards, bench))
            rule, wildcards, bench = m.group(1), {}, None
        elif rule is not None and line.startswith("    wildcards:"):
            wildcards = dict(part.strip().split("=", 1) for part in line.split(":", 1)[1].split(","))
        elif rule is not None and line.startswith("    benchmark:"):
            bench = line.split(":", 1)[1].strip()
        elif rule is not None and (line.startswith("Job stats") or line.startswith("Shell command")):
            jobs.append(Job(rule, wildcards, bench))
            rule = None
    if rule is not None:
        jobs.append(Job(rule, wildcards, bench))
    return jobs


def dag_jobs(target: str) -> list[Job]:
    """The paper profile's jobs of ``target``: a dry run of every job (``--forceall``) in the repository."""
    exe = Path(sys.executable).parent / "snakemake"
    cmd = [str(exe), "-n", "--forceall", "--config", "profile=paper", "--", target]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"project_paper: `{' '.join(cmd)}` failed (exit {proc.returncode}):\n{proc.stderr[-3000:]}")
    jobs = parse_dryrun(proc.stdout + proc.stderr)
    if not jobs:
        raise SystemExit(f"project_paper: `{' '.join(cmd)}` listed no job")
    return jobs


# ---- the paper budgets -------------------------------------------------------------------------------------
def train_work(settings) -> dict[str, dict[str, float]]:
    """{learner: {rate key: work}} of one train job at the paper budget; a rate key names the measured rate that
    consumes the work: ``<learner phase>.<rate>`` of ``bench_learners.py`` or ``environment.<batch>``."""
    m = {name: s.options for name, s in settings.methods.items()}
    ppo, sac, mad, ga, hrl, em, td = (m[k] for k in ("ppo", "sac", "maddpg", "ga_matr", "hrl_tpra", "emorl_tcto",
                                                       "tdmpc"))
    wm = m["dswm"]
    em_rounds = em.n_population * (em.warmup_rounds + em.generations * em.task_rounds)
    em_measured = (em.n_population + em.n_population * (1 + em.generations)) * em.eval_days
    return {
        "ppo": {"train.transitions_per_second": ppo.day_episodes * DAY},
        "sac": {f"environment.{sac.n_envs}": sac.learning_starts,
                "train.transitions_per_second": sac.day_episodes * DAY - sac.learning_starts},
        "maddpg": {"environment.1": mad.warmup, "train.transitions_per_second": mad.transitions - mad.warmup},
        "ga_matr": {"train.transitions_per_second": ga.transitions},
        "hrl_tpra": {"train.transitions_per_second": hrl.day_episodes * DAY},
        "emorl_tcto": {"train.transitions_per_second": (em_rounds * em.n_envs + em_measured) * DAY},
        "tdmpc": {"collect.transitions_per_second": td.precollect.transitions,
                  "gradient.gradient_steps_per_second": td.steps,
                  "play.transitions_per_second": td.episodes * DAY},
        "dswm_world_model": {"collect.transitions_per_second": wm.transitions,
                             "gradient.gradient_steps_per_second": wm.steps},
    }


def eval_days(config: Mapping) -> dict[str, int]:
    """{dataset: test days an evaluation job plans} under the paper profile (every configured ID and OOD day)."""
    out = {}
    for ds in config["profiles"]["paper"]["datasets"]:
        spec = config["datasets"][ds]["eval_days"]
        out[ds] = sum(len(s["values"]) if s["rule"] == "test_positions" else s["count"] for s in spec.values())
    return out


def day_limit(config: Mapping, profile: str, dataset: str) -> int:
    """Test days an evaluation job of ``profile`` plans on ``dataset`` (its eval_days limits, else every day)."""
    return split_days(config, dataset, config["profiles"][profile]["eval_days"])


def split_days(config: Mapping, dataset: str, limits: Mapping[str, int | None]) -> int:
    """Test days of ``dataset`` that ``limits`` ({split: at most this many, None: all}) keep."""
    days = 0
    for split, s in config["datasets"][dataset]["eval_days"].items():
        n = len(s["values"]) if s["rule"] == "test_positions" else s["count"]
        days += n if limits.get(split) is None else min(n, limits[split])
    return days


def extra_days(config: Mapping, settings) -> Callable[[str, str], int]:
    """(dataset, variant name) -> test days an extra run plans under ``settings``' profile (``figures.eval_days``,
    or the foresight grid's or the headroom map's: ``dswm.settings.variant_days``)."""
    from dswm import settings as S

    def days(dataset: str, variant: str) -> int:
        lim = S.variant_days(settings, S.parse_variant(variant))
        return split_days(config, dataset, {"id": lim.id, "ood": lim.ood})

    return days


# ---- the rates ---------------------------------------------------------------------------------------------
def rate(rates: Mapping, learner: str, key: str, case: str) -> float:
    """The measured rate ``key`` of ``learner`` (``environment.<batch>``: the environment's) at ``case``."""
    if key.startswith("environment."):
        node = rates["environment"]["current"]["batches"][key.split(".", 1)[1]]["fleet_slots_per_second"]
    else:
        phase, name = key.split(".", 1)
        node = rates["learners"][learner]["current"][phase][name]
    return float(node[case])


def merge_rates(docs: Sequence[tuple[str, Mapping]]) -> tuple[dict, list[str]]:
    """One rates document from several ``bench_learners.py`` results, later ones overriding earlier ones per
    learner (and the environment's and the planners' rates where a later one has them), with one note per file
    naming what was taken from it. So one learner benchmarked again (``--items tdmpc``) replaces that learner's
    rates only. Every file must hold ``paper`` rates."""
    merged: dict = {"learners": {}}
    notes = []
    for name, doc in docs:
        if doc.get("profile") != "paper":
            raise SystemExit(f"{name}: rates measured under profile {doc.get('profile')!r}, expected 'paper'")
        taken = sorted(doc.get("learners", {}))
        merged["learners"].update(doc.get("learners", {}))
        for key in ("environment", "planners"):
            if key in doc:
                merged[key] = doc[key]
                taken.append(key)
        machine = doc.get("machine", {})
        load = machine.get("load_avg_1min", float("nan"))
        notes.append(f"rates: {name} (quick: {doc.get('quick')}, 1-min load {load:.1f} on {machine.get('cpus')} CPUs "
                     f"when written; code {doc['trees']['current']['rev'][:12]}): {', '.join(taken)}")
    return merged, notes


def plan_ms(rates: Mapping, which: str, case: str) -> float:
    """DSWM's ("dswm") or JTORATC's full solve ("jtoratc_full_solve") ms per decision at ``case``."""
    r = rates["planners"]["current"][which]
    return float(r["median_ms"] if case == "median" else r["min_ms"] if case == "max" else r["max_ms"])


# ---- the projection ----------------------------------------------------------------------------------------
def train_seconds(work: Mapping[str, float], rates: Mapping, learner: str, case: str) -> float:
    return sum(w / rate(rates, learner, key, case) for key, w in work.items() if w)


def job_seconds(job: Job, *, rates, work, days, measured, tdmpc_parallel: int, case: str,
                extra: Extras | None = None) -> tuple[float, str]:
    """(seconds, how) of one job at ``case``; ``extra``: how the figures' jobs are costed (None: as any other job)."""
    w = job.wildcards
    method = w.get("method")
    if job.rule in ("train", "extra_train") and method in WORLD_MODELS:
        return train_seconds(work["dswm_world_model"], rates, "dswm_world_model", case), "measured rates"
    if job.rule in ("train", "extra_train") and method in work:
        return train_seconds(work[method], rates, method, case), "measured rates"
    if job.rule == "evaluate" and method in PLANNERS:
        return days[w["dataset"]] * DAY * plan_ms(rates, "dswm", case) / 1e3, "DSWM plan ms"
    if extra is not None and job.rule == "extra_evaluate":
        if method in PLANNERS:
            return extra.days(w["dataset"], w["variant"]) * DAY * plan_ms(rates, "dswm", case) / 1e3, "DSWM plan ms"
        found = extra.measured(job)
        return found if found is not None else (DEFAULT_S, "default")
    if extra is not None and job.rule == "probe" and method in PLANNERS:
        return extra.probe_points * DAY * plan_ms(rates, "dswm", case) / 1e3, "DSWM plan ms"
    if extra is not None and job.rule == "probe" and method == "tdmpc":
        return extra.probe_points * DAY / rate(rates, "tdmpc", "play.transitions_per_second", case), \
            "TD-MPC MPPI step"
    if job.rule == "evaluate" and method == "jtoratc":
        return days[w["dataset"]] * DAY * plan_ms(rates, "jtoratc_full_solve", case) / 1e3, "JTORATC solve ms"
    if job.rule == "evaluate" and method == "tdmpc":
        slot_s = tdmpc_parallel / rate(rates, "tdmpc", "play.transitions_per_second", case)
        return DAY * slot_s, "TD-MPC MPPI step"
    found = measured(job)
    return found if found is not None else (DEFAULT_S, "default")


Reused = Callable[[str, str, int], bool]
"""(dataset, method, seed) -> whether that evaluate job reuses another seed's evaluation (``dswm.settings.reused_seed``
under one profile's settings)."""


class Extras(NamedTuple):
    """How the figures' jobs are costed (``--target figures``)."""
    days: Callable[[str, str], int]
    """(dataset, variant name) -> the paper's test days of an extra run (:func:`extra_days`)."""
    measured: Callable[[Job], tuple[float, str] | None]
    """An extra run of a method that does not plan: :func:`extra_lookup`."""
    probe_points: int
    """Snapshots a probe job scores on its one day (``figures.sample_efficiency.fractions``)."""


def extra_lookup(root: Path | None, *, paper_days: Callable[[str, str], int],
                 measured_days: Callable[[str, str], int], reused_paper: Reused | None = None,
                 reused_measured: Reused | None = None, main: Callable[[Job], tuple[float, str] | None] | None = None):
    """A function extra_evaluate job -> (seconds, how): the measured extra runs of its method on its dataset (its own
    variant's, else any variant's; none that reused another seed's, ``reused_measured``) under ``root``, per day they
    evaluated (``measured_days``), times the days the job plans (``paper_days``); a run that reuses another seed's
    (``reused_paper``; both with the figures' seeds) costs what ``main`` (:func:`measured_lookup`) says a reused main
    evaluation costs. None where nothing was measured."""
    def lookup(job: Job) -> tuple[float, str] | None:
        w = job.wildcards
        if root is None:
            return None
        if reused_paper is not None and main is not None and reused_paper(w["dataset"], w["method"], int(w["seed"])):
            bench = f"results/benchmarks/evaluate/{w['dataset']}/{w['method']}/seed{w['seed']}.tsv"
            return main(Job("evaluate", {k: w[k] for k in ("dataset", "method", "seed")}, bench))
        base = root / "extra_evaluate" / w["dataset"]

        def evaluated(paths: list[Path]) -> list[Path]:
            return [p for p in paths if reused_measured is None or not reused_measured(
                w["dataset"], w["method"], seed_of(p))]

        paths = evaluated(sorted(base.glob(f"{w['variant']}/{w['method']}/seed*.tsv"))) or \
            evaluated(sorted(base.glob(f"*/{w['method']}/seed*.tsv")))
        if not paths:
            return None
        per_day = statistics.median(read_seconds(p) / measured_days(w["dataset"], p.parts[-3]) for p in paths)
        return per_day * paper_days(w["dataset"], w["variant"]), "benchmark file per day"

    return lookup


def measured_lookup(root: Path | None, *, scale: Mapping[str, float], reused_paper: Reused | None = None,
                    reused_measured: Reused | None = None):
    """A function job -> (seconds, how) from the benchmark files under ``root`` (the job's own, else the median over
    the same path with any seed), evaluations x ``scale[dataset]``; None where nothing was measured.

    An evaluate job that reuses another seed's evaluation (``reused_paper``; ``evaluation.reuse_seed_independent``)
    only checks and rewrites that seed's files: it takes the measured files of reused evaluations of its method
    (``reused_measured`` says which, under the measured run's profile; on any dataset where its own has none),
    unscaled, as they read no day; any other evaluate job takes those of evaluations that ran. Without the two
    functions no job counts as reused."""
    def lookup(job: Job) -> tuple[float, str] | None:
        if root is None or job.benchmark is None:
            return None
        rel = Path(job.benchmark).relative_to("results/benchmarks") if job.benchmark.startswith("results/") \
            else Path(job.benchmark)
        w = job.wildcards
        evaluates = job.rule == "evaluate" and "seed" in w and "method" in w
        reuses = bool(evaluates and reused_paper and reused_paper(w["dataset"], w["method"], int(w["seed"])))

        def same_kind(path: Path) -> bool:     # evaluate/<dataset>/<method>/seed<seed>.tsv
            if not evaluates or reused_measured is None:
                return True
            return reused_measured(path.parts[-3], w["method"], seed_of(path)) == reuses

        own = root / rel
        pattern = re.sub(r"seed\d+", "seed*", str(rel))
        if reuses:    # a reuse reads no day: the method's reused evaluations on any dataset
            pattern = re.sub(rf"^evaluate/{re.escape(w['dataset'])}/", "evaluate/*/", pattern)
        paths = [own] if own.is_file() and same_kind(own) else \
            [p for p in sorted(root.glob(pattern)) if same_kind(p)]
        if not paths:
            return None
        value = statistics.median(read_seconds(p) for p in paths)
        if reuses:
            return value, "benchmark file (reused seed)"
        factor = scale.get(w.get("dataset"), 1.0) if job.rule == "evaluate" else 1.0
        return value * factor, "benchmark file"

    return lookup


def seed_of(path: Path) -> int:
    """The seed of a job's benchmark file, ``.../seed<seed>.tsv``."""
    return int(re.fullmatch(r"seed(\d+)\.tsv", path.name).group(1))


def read_seconds(path: Path) -> float:
    """The ``s`` column of a Snakemake benchmark file (its first row)."""
    head, row = path.read_text().splitlines()[:2]
    return float(dict(zip(head.split("\t"), row.split("\t")))["s"])


def project(jobs: Iterable[Job], *, rates, work, days, measured, tdmpc_parallel: int,
            extra: Extras | None = None) -> dict:
    """{(rule, method or ""): {"jobs", "how", "median"/"max"/"min": core-hours}} over ``jobs``."""
    rows: dict[tuple[str, str], dict] = defaultdict(lambda: {"jobs": 0, "how": set(), **dict.fromkeys(CASES, 0.0)})
    for job in jobs:
        row = rows[(job.rule, job.wildcards.get("method", ""))]
        row["jobs"] += 1
        for case in CASES:
            s, how = job_seconds(job, rates=rates, work=work, days=days, measured=measured,
                                 tdmpc_parallel=tdmpc_parallel, case=case, extra=extra)
            row[case] += s / 3600.0
        row["how"].add(how)
    return dict(rows)


def report(rows: Mapping, *, notes: list[str]) -> str:
    """The table, the subtotals per rule, the assumptions and last ``total: N core-hours``."""
    lines = [f"{'rule':14s} {'method':18s} {'jobs':>5s} {'core-h':>9s} {'range':>17s}  how"]
    by_rule: dict[str, list] = defaultdict(list)
    for (rule, method), row in rows.items():
        by_rule[rule].append((method, row))
    total = dict.fromkeys(CASES, 0.0)
    for rule in sorted(by_rule, key=lambda r: -sum(x["median"] for _, x in by_rule[r])):
        sub = dict.fromkeys(CASES, 0.0)
        for method, row in sorted(by_rule[rule], key=lambda mr: -mr[1]["median"]):
            lines.append(f"{rule:14s} {method or '-':18s} {row['jobs']:5d} {row['median']:9.2f} "
                         f"{row['max']:8.2f}-{row['min']:<8.2f}  {', '.join(sorted(row['how']))}")
            for c in CASES:
                sub[c] += row[c]
        lines.append(f"{rule + ' (all)':33s} {sum(r['jobs'] for _, r in by_rule[rule]):5d} {sub['median']:9.2f} "
                     f"{sub['max']:8.2f}-{sub['min']:<8.2f}")
        for c in CASES:
            total[c] += sub[c]
    lines += ["", *notes, f"range (fastest-slowest repeat of every rate): {total['max']:.1f}-{total['min']:.1f} "
              f"core-hours", f"total: {total['median']:.1f} core-hours"]
    return "\n".join(line.rstrip() for line in lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rates", type=Path, action="append",
                    help="bench_learners.py's result (its 'current' side); given again, a later file's learners "
                         "replace an earlier one's (default: benchmarks/results/learners_cpu_t1.json)")
    ap.add_argument("--target", default="tables", help="the Snakemake target whose jobs are projected")
    ap.add_argument("--after", help="leave out the jobs of this target's DAG (`--target figures --after tables`: "
                                    "what `figures` adds after `tables`)")
    ap.add_argument("--jobs", type=Path, help="a saved `snakemake -n --forceall` output instead of running it")
    ap.add_argument("--measured", type=Path, default=ROOT / "results" / "benchmarks",
                    help="a finished run's results/benchmarks (the jobs not timed by bench_learners.py)")
    ap.add_argument("--measured-profile", default="demo", help="the profile of that run (its test days per job)")
    args = ap.parse_args()
    from dswm import settings as runconfig
    from dswm.config import load_yaml

    config = load_yaml(ROOT / "config.yaml")
    files = [p.resolve() for p in args.rates or [HERE / "results" / "learners_cpu_t1.json"]]
    rates, rate_notes = merge_rates([(str(p.relative_to(ROOT) if p.is_relative_to(ROOT) else p),
                                      json.loads(p.read_text())) for p in files])
    settings = runconfig.resolve({**config, "profile": "paper"})
    there = runconfig.resolve({**config, "profile": args.measured_profile})
    jobs = parse_dryrun(args.jobs.read_text()) if args.jobs else dag_jobs(args.target)
    before = len(jobs)
    if args.after:
        held = {(j.rule, tuple(sorted(j.wildcards.items()))) for j in dag_jobs(args.after)}
        jobs = [j for j in jobs if (j.rule, tuple(sorted(j.wildcards.items()))) not in held]
    days = eval_days(config)
    root = args.measured if args.measured.is_dir() else None
    scale = {ds: days[ds] / day_limit(config, args.measured_profile, ds) for ds in days}
    main_lookup = measured_lookup(root, scale=scale,
                                  reused_paper=lambda *k: runconfig.reused_seed(settings, *k) is not None,
                                  reused_measured=lambda *k: runconfig.reused_seed(there, *k) is not None)
    def reused_extra(s):     # an extra run that reuses another seed's under the settings ``s``
        return lambda ds, m, seed: runconfig.reused_seed(s, ds, m, seed, runconfig.figure_seeds(s, ds)) is not None

    extra = Extras(days=extra_days(config, settings), probe_points=len(settings.figures.sample_efficiency.fractions),
                   measured=extra_lookup(root, paper_days=extra_days(config, settings),
                                         measured_days=extra_days(config, there), main=main_lookup,
                                         reused_paper=reused_extra(settings), reused_measured=reused_extra(there)))
    rows = project(jobs, rates=rates, work=train_work(settings), days=days, measured=main_lookup,
                   tdmpc_parallel=settings.methods["tdmpc"].options.parallel, extra=extra)
    after = f", less the {before - len(jobs)} of `{args.after}`" if args.after else ""
    notes = [*rate_notes,
             f"jobs: {len(jobs)} of `snakemake -n --forceall --config profile=paper {args.target}`{after}",
             f"test days per evaluation: {days}; other jobs: {root or 'no measured run'} (evaluations x paper days /"
             f" {args.measured_profile} days), else {DEFAULT_S:.0f} s",
             "one job = one core; DSWM+'s and the probes' planners cost DSWM's plan; SAC's and MADDPG's random "
             "transitions at the environment's rate",
             "figures: an extra_train as its method's train job; an extra run of a planner its days x DSWM's plan, of "
             "another method the measured extra runs' seconds per day x its days; a probe of a planner (TD-MPC) "
             f"{extra.probe_points} snapshots x one day of DSWM's plan (of MPPI), of another method its measured "
             "file; wm_quality its measured file, unscaled"]
    print(report(rows, notes=notes))


if __name__ == "__main__":
    main()
