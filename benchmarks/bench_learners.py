"""Training throughput of every learner at the paper profile's sizes on one thread, the environment's ceiling and
DSWM's planning time beside JTORATC's, optionally side by side with a baseline revision.

Run: python benchmarks/bench_learners.py [--tensor results/data/milan] [--quick] [--baseline REV]
Writes benchmarks/results/learners_cpu_t1.json (``--out`` elsewhere).

Each item runs in its own Python process with one thread (``torch.set_num_threads(1)``, OMP_NUM_THREADS and
MKL_NUM_THREADS = 1) and PYTHONPATH at the measured tree's ``src``; the settings are that tree's config.yaml under
the selected profile (``--profile``, default ``paper``), resolved by the settings code the jobs use
(``dswm.settings.resolve``: each method's ``options_from_config``), on the training days of a prepared tensor
(``dswm.pipeline.setup.training_core``).

* ``environment``: one day of uniform random actions through ``FleetCore.step`` (``bench_env.bench_core``) at each
  batch the learners step (their n_envs, parallel days, one day for MADDPG's PettingZoo env): the ceiling of any
  learner's transitions per second.
* one entry per learner (:data:`LEARNERS`): its real ``fit``, ended once enough units of its budget are timed
  (``_learner_probes``): PPO, SAC (rounds of n_envs days), MADDPG (day-episodes), GA-MATR, HRL-TPRA (rounds),
  EMORL-TCTO (tasks), TD-MPC (gradient steps of its seed phase, then the core steps of its own MPPI episodes) and
  DSWM's world model (the gradient steps of ``dswm.methods.dswm.training.train`` after its pre-collection, whose
  core steps are timed too). Transitions and gradient steps per second at the median of the repeats, with the
  slowest and the fastest repeat.
* ``planners``: DSWM's plan (Algorithm 1 at the profile's CEM N/I/H/K, compiled where the profile compiles) and
  JTORATC's full solve (its degradation rule off) per decision on the same slots of the first test day
  (``_decisions.time_decisions``, as ``bench_methods.py``).

Every figure is a warm-up, then the median of at least 5 repeats with min and max. ``--quick`` times the fewest
units (1 warm-up, 5 repeats of one unit, 5 planned slots): a check that every probe runs, not a benchmark; with
``--parallel 2`` two items' workers run at once (the JSON records it), which halves a check's wall time. The
counts are sized to keep a run under ~15 min on an idle core (GA-MATR's rounds and EMORL-TCTO's tasks are the
longest units); ``--baseline`` doubles it.

``--baseline REV``: a git worktree of REV is made under a temporary directory and removed at the end; every item
is measured in both trees in the same run, alternating which goes first, and the JSON holds both and the speed-up
of each learner (current / baseline of its headline rate; the planner's: baseline ms / current ms), with the goal
(3x for the world model's training step, SAC, TD-MPC, MADDPG and DSWM's planner) beside it. Both sides must
resolve to the same settings (``settings_hash``); the JSON says whether they did.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
LEARNERS = ("dswm_world_model", "ppo", "sac", "maddpg", "tdmpc", "ga_matr", "hrl_tpra", "emorl_tcto")
"""The learners measured (``dswm_world_model``: the training of DSWM's world model, which all DSWM methods share)."""
ITEMS = ("environment", *LEARNERS, "planners")
HEADLINE = {"dswm_world_model": "gradient.gradient_steps_per_second", "ppo": "train.transitions_per_second",
            "sac": "train.gradient_steps_per_second", "maddpg": "train.transitions_per_second",
            "tdmpc": "gradient.gradient_steps_per_second", "ga_matr": "train.transitions_per_second",
            "hrl_tpra": "train.transitions_per_second", "emorl_tcto": "train.transitions_per_second"}
"""The rate a learner's speed-up is taken on (phase.rate)."""
GOALS = {"dswm_world_model": 3.0, "sac": 3.0, "tdmpc": 3.0, "maddpg": 3.0}
"""Speed-up goals (issue: the world model's training step, SAC, TD-MPC, MADDPG and DSWM's planner >= 3x)."""
PLANNER_GOAL = 3.0
DSWM_OVER_JTORATC_GOAL = 1 / 3
"""DSWM's plan at most a third of JTORATC's full solve per decision."""


# ---- one item, in a worker process ------------------------------------------------------------------------
def counts(quick: bool):
    from _learner_probes import Counts

    if quick:
        return {"rounds": Counts(1, 5), "steps": Counts(1, 5), "play": Counts(1, 5), "env_repeats": 5, "slots": 5}
    # a round of GA-MATR or a task of EMORL-TCTO at paper size is the longest unit: the fewest of those
    return {"rounds": Counts(1, 5), "steps": Counts(3, 5, 4), "play": Counts(2, 5, 2), "env_repeats": 5,
            "slots": 12}


def resolved(tree: Path, profile: str):
    """The tree's config.yaml resolved under ``profile``, with every measured method in ``methods.run``."""
    from dswm import settings as runconfig
    from dswm.config import load_yaml

    config = load_yaml(tree / "config.yaml")
    wanted = [m for m in LEARNERS if m != "dswm_world_model"] + ["dswm", "jtoratc"]
    config["methods"]["run"] = list(dict.fromkeys([*config["methods"]["run"], *wanted]))
    config["methods"].pop("only_on", None)
    return runconfig.resolve({**config, "profile": profile})


def settings_hash(options) -> str:
    from dswm.config import stable_hash, to_plain

    return stable_hash(to_plain(options), length=12)


def measure_learner(name: str, settings, core, c: dict) -> dict:
    import _learner_probes as P

    method = "dswm" if name == "dswm_world_model" else name
    m = settings.methods[method]
    cls, o = m.controller_class, m.options
    if name == "dswm_world_model":
        o = cls.training_settings(o)
        steps = c["steps"].units
        out = P.step_probe(method, cls, o, core, c["steps"], changes={
            "transitions": P.DAY * o.training.collect_parallel, "steps": max(o.steps, steps + 1),
            "training": {"checkpoint_every": P.NEVER}})
        out["transitions_per_second"] = out["collect"]["transitions_per_second"]
    elif name == "tdmpc":
        steps = c["steps"].units
        out = P.step_probe(method, cls, o, core, c["steps"], play=c["play"], changes={
            "precollect": {"transitions": P.DAY * o.precollect.collect_parallel}, "seed_steps": steps,
            "episodes": o.parallel, "steps": steps + P.DAY * o.parallel, "checkpoint_every": P.NEVER})
        out["transitions_per_second"] = out["play"]["transitions_per_second"]
    elif name in ("ppo", "sac"):
        out = P.sb3_probe(method, cls, o, core, c["rounds"], extra={"learning_starts": 0} if name == "sac" else None)
    elif name == "emorl_tcto":
        out = P.emorl_probe(method, cls, o, core, c["rounds"])
    else:
        per_unit = P.DAY * (o.n_envs if name != "maddpg" else 1)
        key = "day_episodes" if name == "hrl_tpra" else "transitions"
        ramp = 0
        changes = {"checkpoint_every": P.NEVER}
        if name == "maddpg":   # no random warm-up; the days until the replay holds a batch are not timed
            ramp = -(-o.batch_size // P.DAY)
            changes["warmup"] = 0
        units = ramp + c["rounds"].units
        changes[key] = units * (o.n_envs if key == "day_episodes" else per_unit)
        out = P.trained_probe(method, cls, o, core, c["rounds"], changes=changes, ramp=ramp)
    if "train" in out:
        out["transitions_per_second"] = out["train"]["transitions_per_second"]
        out["gradient_steps_per_second"] = out["train"]["gradient_steps_per_second"]
    else:
        out["gradient_steps_per_second"] = out["gradient"]["gradient_steps_per_second"]
    return {"method": method, "settings_hash": settings_hash(o), **out}


def env_batches(settings) -> list[int]:
    """The batches the learners step the core at: their n_envs, parallel days; 1 for MADDPG."""
    ms = settings.methods
    dswm = ms["dswm"].options.training.collect_parallel
    return sorted({1, dswm, ms["tdmpc"].options.parallel,
                   *(ms[m].options.n_envs for m in ("ppo", "sac", "ga_matr", "hrl_tpra", "emorl_tcto"))})


def measure_item(item: str, *, tree: Path, tensor_dir: Path, profile: str, quick: bool) -> dict:
    """Measure one item in this process (one thread)."""
    import math

    import torch

    torch.set_num_threads(1)
    import dswm
    from _decisions import first_test_day, planning_controller, scenario_for, time_decisions
    from dswm.pipeline.allocator import keep_freed_memory
    from dswm.pipeline.setup import training_core
    from dswm.sim.core import core_from_tensor
    from prep.tensor import load

    try:   # as every job does (dswm.pipeline.setup.init_process); a tree from before subnormal flushing does not
        from dswm.pipeline.setup import prepare_process
    except ImportError:
        flushed = False
        keep_freed_memory()
    else:
        flushed = prepare_process(1)
    settings = resolved(tree, profile)
    tensor = load(tensor_dir)
    record = tensor_dir.parents[1] / "calibration" / "demand_intensity.json"
    scenario, source = scenario_for(settings, record)
    c = counts(quick)
    head = {"item": item, "dswm_imported_from": str(Path(dswm.__file__).parent), "intensity_from": source,
            "threads": torch.get_num_threads(), "subnormals_flushed": flushed}
    if item == "environment":
        from bench_env import bench_core

        core = training_core(tensor, scenario)
        return {**head, "batches": {str(b): bench_core(core, b, repeats=c["env_repeats"])
                                    for b in env_batches(settings)}}
    if item == "planners":
        day = first_test_day(tensor)
        start, slots = 54, c["slots"]
        out = {}
        for label, method, over in (("dswm", "dswm", {}), ("jtoratc_full_solve", "jtoratc",
                                                          {"solve_budget_ms": math.inf})):
            ctl = planning_controller(settings, method, core_from_tensor(tensor, scenario, [day]), **over)
            out[label] = time_decisions(ctl, tensor, scenario, day, start, slots)
            out[label]["settings_hash"] = settings_hash(settings.methods[method].options)
        planner = settings.methods["dswm"].options.planner
        return {**head, "day": tensor.labels[day], "start_slot": start,
                "dswm_planner": {k: getattr(planner, k) for k in ("n_samples", "iterations", "horizon", "n_elites",
                                                                  "compile")},
                **out, "dswm_over_jtoratc": out["dswm"]["median_ms"] / out["jtoratc_full_solve"]["median_ms"]}
    core = training_core(tensor, scenario)
    return {**head, **measure_learner(item, settings, core, c)}


# ---- the run: items in subprocesses, both sides alternating ------------------------------------------------
class ItemFailed(RuntimeError):
    """One item's worker process failed; the run records it and goes on with the other items."""


def run_side(item: str, side: str, tree: Path, args, scratch: Path) -> dict:
    """Measure ``item`` with ``tree``'s code (the ``side``'s) in a fresh one-thread process."""
    out = scratch / f"{item}-{side}.json"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tree / "src"), str(tree)]), "OMP_NUM_THREADS": "1",
           "MKL_NUM_THREADS": "1"}
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", item, "--tree", str(tree),
           "--tensor", str(args.tensor), "--profile", args.profile, "--out", str(out), *(["--quick"] * args.quick)]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        raise ItemFailed(f"bench_learners: {item} in {tree} failed (exit {proc.returncode}):\n{proc.stderr[-4000:]}")
    result = json.loads(out.read_text())
    if not Path(result["dswm_imported_from"]).is_relative_to(tree):
        raise SystemExit(f"bench_learners: {item} imported dswm from {result['dswm_imported_from']}, expected "
                         f"{tree / 'src'}; an installed copy shadows PYTHONPATH")
    result["wall_s"] = round(time.perf_counter() - t0, 1)
    print(f"  {item:18s} {side:9s} {result['wall_s']:7.1f} s", flush=True)
    return result


def dig(result: dict, path: str) -> float:
    """The median of ``phase.rate`` in a learner's result."""
    node = result
    for key in path.split("."):
        node = node[key]
    return node["median"]


def rates(result: dict) -> dict[str, float]:
    """Every median rate of a learner's result, by "phase.rate"."""
    return {f"{p}.{r}": result[p][r]["median"] for p in ("train", "gradient", "collect", "play") if p in result
            for r in ("transitions_per_second", "gradient_steps_per_second") if result[p].get(r)}


def compare(name: str, current: dict, baseline: dict | None) -> dict:
    entry = {"headline": HEADLINE[name], "goal_speedup": GOALS.get(name), "current": current, "baseline": baseline}
    if "error" in current or (baseline is not None and "error" in baseline):
        return entry
    if baseline is not None:
        cur, base = rates(current), rates(baseline)
        entry["speedups"] = {k: round(cur[k] / base[k], 3) for k in cur if k in base}
        entry["speedup"] = entry["speedups"][HEADLINE[name]]
        entry["same_settings"] = current["settings_hash"] == baseline["settings_hash"]
        entry["goal_met"] = None if name not in GOALS else entry["speedup"] >= GOALS[name]
    return entry


def git(*args: str, cwd: Path = ROOT) -> str:
    return subprocess.run(["git", *args], cwd=cwd, check=True, capture_output=True, text=True).stdout.strip()


def tree_record(tree: Path) -> dict:
    return {"tree": str(tree), "rev": git("rev-parse", "HEAD", cwd=tree),
            "dirty": bool(git("status", "--porcelain", "--untracked-files=no", cwd=tree))}


def orchestrate(args) -> dict:
    sides = {"current": ROOT}
    with tempfile.TemporaryDirectory(prefix="bench-learners-") as tmp:
        scratch = Path(tmp)
        if args.baseline:
            base = scratch / "baseline"
            git("worktree", "add", "--detach", str(base), args.baseline)
            sides["baseline"] = base
        try:
            trees = {side: tree_record(tree) for side, tree in sides.items()}

            def measure(i: int, item: str) -> dict:
                order = list(sides) if i % 2 == 0 else list(reversed(sides))
                by_side = {}
                for side in order:
                    try:
                        by_side[side] = run_side(item, side, sides[side], args, scratch)
                    except ItemFailed as exc:   # the other items still run; the JSON names the failure
                        print(exc, file=sys.stderr, flush=True)
                        by_side[side] = {"error": str(exc)}
                return by_side

            # Items one after another (each worker alone on the machine: its rates mean something), or --parallel
            # at once where the run only checks that every probe runs (tests/test_bench_tools.py).
            with ThreadPoolExecutor(max_workers=args.parallel) as pool:
                futures = {item: pool.submit(measure, i, item) for i, item in enumerate(args.items)}
            results = {item: future.result() for item, future in futures.items()}
        finally:
            if args.baseline:
                git("worktree", "remove", "--force", str(sides["baseline"]))
    payload = {"profile": args.profile, "quick": args.quick, "parallel": args.parallel, "tensor": str(args.tensor),
               "threads": 1, "load_avg_1min_start": args.load0, "trees": trees,
               "learners": {n: compare(n, results[n]["current"], results[n].get("baseline"))
                            for n in LEARNERS if n in results}}
    if "environment" in results:
        payload["environment"] = results["environment"]
    failed = [f"{item} ({side})" for item, by_side in results.items() for side, r in by_side.items() if "error" in r]
    payload["failed"] = failed
    if "planners" in results and "error" not in results["planners"]["current"]:
        cur, base = results["planners"]["current"], results["planners"].get("baseline")
        base = None if base is not None and "error" in base else base
        p = {"current": cur, "baseline": base, "goal_dswm_over_jtoratc": DSWM_OVER_JTORATC_GOAL,
             "goal_met_dswm_over_jtoratc": cur["dswm_over_jtoratc"] <= DSWM_OVER_JTORATC_GOAL,
             "goal_speedup": PLANNER_GOAL}
        if base is not None:
            p["speedup"] = round(base["dswm"]["median_ms"] / cur["dswm"]["median_ms"], 3)
            p["goal_met"] = p["speedup"] >= PLANNER_GOAL
            p["same_settings"] = cur["dswm"]["settings_hash"] == base["dswm"]["settings_hash"]
        payload["planners"] = p
    return payload


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tensor", type=Path, default=Path("results/data/milan"), help="a prepared tensor directory")
    ap.add_argument("--profile", default="paper", help="the config profile whose sizes are measured")
    ap.add_argument("--quick", action="store_true", help="fewest units: a check that every probe runs")
    ap.add_argument("--parallel", type=int, default=1, metavar="N",
                    help="run N items' workers at once (default 1: each alone, as timings need; more only for a "
                         "check that every probe runs, whose rates then share the machine)")
    ap.add_argument("--baseline", metavar="REV", help="also measure git revision REV, side by side")
    ap.add_argument("--items", nargs="+", default=list(ITEMS), choices=ITEMS, help="what to measure (default all)")
    ap.add_argument("--out", type=Path, default=None, help="result file (default benchmarks/results/"
                                                           "learners_cpu_t1.json)")
    ap.add_argument("--worker", choices=ITEMS, help=argparse.SUPPRESS)
    ap.add_argument("--tree", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args()
    args.tensor = args.tensor.resolve()
    if not (args.tensor / "meta.json").is_file():
        raise SystemExit(f"{args.tensor}: no prepared tensor (meta.json); expected the output of the prepare rule, "
                         f"e.g. `snakemake --cores 2 results/data/milan/meta.json`")
    if args.worker:
        result = measure_item(args.worker, tree=args.tree, tensor_dir=args.tensor, profile=args.profile,
                              quick=args.quick)
        args.out.write_text(json.dumps(result, indent=2) + "\n")
        return
    if args.parallel < 1:
        raise SystemExit(f"bench_learners: --parallel must be at least 1, found {args.parallel}")
    args.load0 = os.getloadavg()[0]
    payload = orchestrate(args)
    from _timing import write_to

    path = write_to(args.out or HERE / "results" / "learners_cpu_t1.json", payload)
    print(f"wrote {path}")
    if payload["failed"]:
        raise SystemExit(f"bench_learners: failed: {', '.join(payload['failed'])} (their errors are in {path})")


if __name__ == "__main__":
    main()
