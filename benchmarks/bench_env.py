"""Environment throughput: B parallel one-day episodes with random actions, fleet-slots per second.

Run: python benchmarks/bench_env.py [--episodes 256] [--threads 2] [--repeats 5]
(writes benchmarks/results/env.json). Target: >= 10,000 fleet-slots/s.

One measurement is one day: ``FleetCore.step`` 143 times on B episodes (the reset before it is not timed). A
warm-up day comes first (numba's compilation, torch's allocations), then ``--repeats`` days are timed; the figures
are their median with the min and max.
"""
from __future__ import annotations

import argparse

import numpy as np
import torch

from _timing import rate, timed, write
from dswm.sim.core import FleetCore, Grid, initial_positions
from dswm.sim.env import default_scenario, synthetic_demand


def bench_core(core: FleetCore, episodes: int, *, repeats: int, seed: int = 0) -> dict:
    """One day of ``core.step`` on ``episodes`` episodes with uniform random actions: timing and fleet-slots/s."""
    scenario = core.scenario
    slots = scenario.slots_per_day - 1
    actions = np.random.default_rng(seed).uniform(
        -1, 1, (slots, episodes, scenario.n_uavs, 3)).astype(np.float32)

    def day():
        for a in actions:
            core.step(a)

    timing = timed(day, setup=lambda: core.reset(np.arange(episodes) % core.n_days), repeats=repeats)
    return {"episodes": episodes, "slots": slots, "seconds": timing,
            "fleet_slots_per_second": rate(timing, episodes * slots)}


def demo_core(days: int = 8) -> FleetCore:
    """The benchmark's core: 20 x 20 cells of 235 m (the demo grid), the config scenario, synthetic demand."""
    scenario = default_scenario()
    grid = Grid(rows=20, cols=20, cell_m=235.0)
    demand = synthetic_demand(days=days, rows=20, cols=20, slots=scenario.slots_per_day)
    return FleetCore(demand=demand, grid=grid, scenario=scenario, dataset="bench",
                     init_pos=initial_positions(demand.mean(axis=(0, 1)), grid, scenario.n_uavs, 0),
                     day_labels=[f"d{i}" for i in range(days)])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--episodes", type=int, default=256)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    # imported here: bench_learners imports bench_core into a baseline tree, which may predate prepare_process
    from dswm.pipeline.setup import prepare_process

    prepare_process(args.threads)   # as every job does (dswm.pipeline.setup.init_process)
    result = bench_core(demo_core(), args.episodes, repeats=args.repeats)
    write("env", {**result, "target_fleet_slots_per_second": 10_000})


if __name__ == "__main__":
    main()
