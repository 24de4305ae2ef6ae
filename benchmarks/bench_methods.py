"""Per-decision planning time of the optimization baselines beside DSWM's and Greedy's, in ONE run.

Run: python benchmarks/bench_methods.py [--tensor results/data/milan] [--day test] [--start-slot 54] [--slots 12]
Writes benchmarks/results/methods_cpu_t<threads>.json.

Every method plans the same slots of the same day of a prepared tensor (default: the first test day of the Milan
tensor of the selected profile, ``snakemake --cores 2 results/data/milan/meta.json`` writes it), one day alone
(batch of one), with the settings config.yaml gives it:

* ``greedy``: the project's one BCD search (``search``);
* ``ins_woa``: its whale optimization at the configured population and iterations;
* ``jtoratc (full solve)``: every decision a complete BCD solve (the degradation rule off), the cost the paper's
  degradation rule reacts to; ``jtoratc (configured)`` is the method as evaluated, rule included;
* ``dswm``: Algorithm 1 at the demo planner size and at the paper's production size (compiled where the paper
  profile compiles); weights untrained, which does not change the cost.

The fleet holds its initial deployment until ``--start-slot`` (09:00 by default: daytime demand), then each
method decides ``--slots`` consecutive slots, stepping the environment with its own actions; the first decided
slot (one-time allocations, cvxpy's and torch's compiling) is reported apart. Ratios are against JTORATC's full
solve. The machine's load is recorded; run it on an idle machine.
"""
from __future__ import annotations

import argparse
import copy
import math
from pathlib import Path

import torch
import yaml

from _decisions import first_test_day, planning_controller, scenario_for, time_decisions
from _timing import write
from dswm import settings as runconfig
from dswm.sim.core import core_from_tensor

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tensor", default="results/data/milan", help="a prepared tensor directory")
    ap.add_argument("--day", default="test", help="'test' (its first test day) or a tensor day index")
    ap.add_argument("--start-slot", type=int, default=54, help="first decided slot (54 = 09:00)")
    ap.add_argument("--slots", type=int, default=12, help="decisions timed per method, after the first")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    from prep.tensor import load

    tensor_dir = ROOT / args.tensor
    if not (tensor_dir / "meta.json").is_file():
        raise SystemExit(f"{tensor_dir}: no prepared tensor (meta.json); expected the output of the prepare rule, "
                         f"e.g. `snakemake --cores 2 {args.tensor}/meta.json`")
    tensor = load(tensor_dir)
    if args.day == "test":
        day = first_test_day(tensor)
    else:
        day = int(args.day)
    config = yaml.safe_load((ROOT / "config.yaml").read_text())
    config["methods"]["run"] = list(dict.fromkeys([*config["methods"]["run"], "greedy", "ins_woa", "jtoratc",
                                                   "dswm"]))
    config["methods"].pop("only_on", None)
    demo = runconfig.resolve({**copy.deepcopy(config), "profile": "demo"})
    paper = runconfig.resolve({**copy.deepcopy(config), "profile": "paper"})
    scenario, source = scenario_for(demo, ROOT / runconfig.CALIBRATION_RECORD, ROOT)
    print(f"timing day {tensor.labels[day]} of {args.tensor}, slots {args.start_slot}..{args.start_slot + args.slots}"
          f", u from {source}")
    load0 = __import__("os").getloadavg()[0]
    runs = {
        "greedy": (demo, "greedy", {}),
        "ins_woa": (demo, "ins_woa", {}),
        "jtoratc (full solve)": (demo, "jtoratc", {"solve_budget_ms": math.inf}),
        "jtoratc (configured)": (demo, "jtoratc", {}),
        "dswm (demo planner)": (demo, "dswm", {}),
        "dswm (paper planner, production)": (paper, "dswm", {}),
    }
    per_method = {}
    for name, (settings, method, over) in runs.items():
        ctl = planning_controller(settings, method, core_from_tensor(tensor, scenario, [day]), **over)
        per_method[name] = time_decisions(ctl, tensor, scenario, day, args.start_slot, args.slots)
        print(f"{name:34s} median {per_method[name]['median_ms']:9.1f} ms per decision", flush=True)
    ref = per_method["jtoratc (full solve)"]["median_ms"]
    ratios = {f"jtoratc full solve / {name}": round(ref / r["median_ms"], 2)
              for name, r in per_method.items() if not name.startswith("jtoratc (full")}
    goal = "dswm (paper planner, production)"
    payload = {"tensor": args.tensor, "day": tensor.labels[day], "start_slot": args.start_slot, "slots": args.slots,
               "threads": args.threads, "intensity_from": source, "load_avg_1min_start": load0,
               "per_decision": per_method, "ratios": ratios,
               "goal": {"statement": "DSWM's production planning at least 10x faster than JTORATC's full solve",
                        "ratio": ratios[f"jtoratc full solve / {goal}"],
                        "met": ratios[f"jtoratc full solve / {goal}"] >= 10.0}}
    write(f"methods_cpu_t{args.threads}", payload)


if __name__ == "__main__":
    main()
