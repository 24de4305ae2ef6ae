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
import dataclasses
import math
import statistics
import time
from pathlib import Path

import numpy as np
import torch
import yaml

from _timing import write
from dswm import settings as runconfig
from dswm.methods.base import DayContext
from dswm.sim.core import core_from_tensor
from dswm.sim.scenario import DEMO_INTENSITY

ROOT = Path(__file__).resolve().parents[1]


def _scenario(settings: runconfig.Settings):
    """The configured scenario; u from the calibrate record when there is one, else the demo's stand-in."""
    record = ROOT / runconfig.CALIBRATION_RECORD
    if settings.scenario.calibrates:
        if record.is_file():
            return runconfig.calibrated_scenario(settings.scenario, record), str(record.relative_to(ROOT))
        return dataclasses.replace(settings.scenario, demand_intensity=DEMO_INTENSITY), "DEMO_INTENSITY stand-in"
    return settings.scenario, "config.yaml"


def _controller(settings: runconfig.Settings, method: str, core, **options):
    m = settings.methods[method]
    opts = dataclasses.replace(m.options, **options) if options else m.options
    ctl = m.controller_class(name=method, seed=0, device="cpu", options=opts)
    if m.learns:  # untrained weights: planning costs the same
        ctl.model = ctl._build_model(core.grid, core.scenario)
        ctl.model.set_normalizer(torch.as_tensor(core.demand[:1].cpu().numpy()))
        ctl.model.eval()
    return ctl


def _time(ctl, tensor, scenario, day: int, start: int, slots: int) -> dict:
    """Median, p90 and spread of per-decision ms over ``slots`` decisions from ``start`` (the first apart)."""
    core = core_from_tensor(tensor, scenario, [day])
    grid = core.grid
    ctx = DayContext(dataset=tensor.meta["dataset"], day=day, label=tensor.labels[day], split="id", grid=grid,
                     scenario=scenario, geometry=grid.geometry(), cells=grid.cells(), init_pos=core.init_pos.numpy(),
                     device="cpu", demand=tensor.demand[day] if ctl.clairvoyant else None)
    obs = core.reset([0])
    if ctl.batched:
        ctl.reset_batch([ctx])
    else:
        ctl.reset(ctx)
    hold = np.zeros((1, scenario.n_uavs, 3), dtype=np.float32)
    for _ in range(start):
        obs = core.step(hold).obs
    times, served = [], []
    for _ in range(slots + 1):
        t0 = time.perf_counter()
        action = ctl.act_batch(obs) if ctl.batched else ctl.act({k: v[0] for k, v in obs.items()})[None]
        times.append(1e3 * (time.perf_counter() - t0))
        out = core.step(action)
        obs = out.obs
        served.append(float(np.asarray(out.sr).mean()))
    first, times = times[0], times[1:]
    out = {"median_ms": round(statistics.median(times), 1), "p90_ms": round(float(np.percentile(times, 90)), 1),
           "min_ms": round(min(times), 1), "max_ms": round(max(times), 1), "first_slot_ms": round(first, 1),
           "served_ratio_mean": round(statistics.mean(served), 4)}
    if hasattr(ctl, "day_stats"):
        stats = ctl.day_stats()
        if stats and stats[0]:
            out["day_stats"] = {k: round(v, 2) for k, v in stats[0].items()}
    return out


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
        day = next(d["index"] for d in tensor.meta["days"] if d["split"] == "test")
    else:
        day = int(args.day)
    config = yaml.safe_load((ROOT / "config.yaml").read_text())
    config["methods"]["run"] = list(dict.fromkeys([*config["methods"]["run"], "greedy", "ins_woa", "jtoratc",
                                                   "dswm"]))
    config["methods"].pop("only_on", None)
    demo = runconfig.resolve({**copy.deepcopy(config), "profile": "demo"})
    paper = runconfig.resolve({**copy.deepcopy(config), "profile": "paper"})
    scenario, source = _scenario(demo)
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
        ctl = _controller(settings, method, core_from_tensor(tensor, scenario, [day]), **over)
        per_method[name] = _time(ctl, tensor, scenario, day, args.start_slot, args.slots)
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
