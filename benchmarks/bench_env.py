"""Environment throughput: B parallel one-day episodes with random actions, fleet-slots per second.

Run: python benchmarks/bench_env.py   (writes benchmarks/results/env.json). Target: >= 10,000 fleet-slots/s.
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from _timing import write
from dswm.pipeline.allocator import keep_freed_memory
from dswm.sim.core import FleetCore, Grid, initial_positions
from dswm.sim.env import default_scenario, synthetic_demand


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--episodes", type=int, default=256)
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    keep_freed_memory()   # as every job does (dswm.pipeline.jobs)
    scenario = default_scenario()
    grid = Grid(rows=20, cols=20, cell_m=235.0)
    demand = synthetic_demand(days=8, rows=20, cols=20, slots=scenario.slots_per_day)
    core = FleetCore(demand=demand, grid=grid, scenario=scenario, dataset="bench",
                     init_pos=initial_positions(demand.mean(axis=(0, 1)), grid, scenario.n_uavs, 0),
                     day_labels=[f"d{i}" for i in range(8)])
    rng = np.random.default_rng(0)
    actions = rng.uniform(-1, 1, (scenario.slots_per_day - 1, args.episodes, scenario.n_uavs, 3)).astype(np.float32)
    core.reset(np.arange(args.episodes) % 8)
    t0 = time.perf_counter()
    for a in actions:
        core.step(a)
    elapsed = time.perf_counter() - t0
    rate = args.episodes * len(actions) / elapsed
    write("env", {"episodes": args.episodes, "slots": len(actions), "seconds": round(elapsed, 3),
                  "fleet_slots_per_second": round(rate), "target_fleet_slots_per_second": 10_000})


if __name__ == "__main__":
    main()
