"""Does eq. 7's reward order simple policies as the served ratio does? Hold, Static, and Static with every UAV flying
back and forth around its spot, on the learning curves' validation days.

Run (from a workflow root whose results/data/<dataset> exists, e.g. after `snakemake learning`):
    python benchmarks/diagnose_reward.py [--profile demo] [--legs 750 1500]

The energy term of the reward favours motion (a rotary-wing UAV at low speed draws less power than hovering), so a
learner could trade served ratio for energy. One JSON line per policy: its served ratio, reward per day and energy
per slot, in the evaluation's environment and initial fleet (the learning score job's scenario, the calibration
record read where the workflow wrote one), on the validation days of `learning` (never a test day):
* ``hold``: every action zero all day (a recharged UAV stays at its station);
* ``static``: Static's rule (fly to the K-means spot, at most D_max per slot);
* ``static_legs_<L>``: Static's spot plus or minus L/2 metres east, alternating each slot (legs of L metres).
A last line gives the power of flying D_max in a slot relative to hovering.
"""
from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import numpy as np
import torch

from _learning_job import learning_job
from dswm.methods.search import to_action
from dswm.protocol.learning import learning_days
from dswm.sim.core import core_from_tensor, fleet_state_from_obs
from dswm.sim.energy import hover_power, rotor_power


def run(tensor, scenario, days: list[int], leg_m: float | None) -> dict:
    """One policy on ``days`` (batched): None holds still; a number flies legs of that length around Static's spot
    (0: Static itself)."""
    core = core_from_tensor(tensor, scenario, days)
    obs = core.reset(list(range(len(days))))
    home = core.init_pos.float()
    rewards, srs, energy = [], [], []
    for k in range(scenario.slots_per_day - 1):
        state = fleet_state_from_obs(torch.as_tensor(obs["fleet"]), core.grid, scenario)
        if leg_m is None:
            move = torch.zeros_like(state.pos)
        else:
            target = home.expand_as(state.pos).clone()
            target[..., 0] += (leg_m / 2) * (1.0 if k % 2 == 0 else -1.0)
            move = to_action(target, state.pos, scenario.d_max_m)
        out = core.step(torch.cat([move, torch.zeros_like(move[..., :1])], dim=-1).numpy())
        obs = out.obs
        rewards.append(out.reward)
        srs.append(out.sr)
        energy.append(out.energy_j)
    return {"served_ratio": round(float(np.mean(srs)), 4),
            "reward_per_day": round(float(np.sum(rewards, axis=0).mean()), 2),
            "energy_kj_per_slot": round(float(np.mean(energy)) / 1e3, 1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--root", type=Path, default=Path.cwd(), help="workflow root (config.yaml, results/data)")
    ap.add_argument("--profile", default="demo")
    ap.add_argument("--legs", type=float, nargs="*", default=[750.0, 1500.0], help="leg lengths in metres")
    args = ap.parse_args()
    os.chdir(args.root)
    torch.set_num_threads(1)
    s, tensor, learning, job = learning_job(args.root.resolve(), args.profile, "static", "score")
    _, val = learning_days(tensor, int(job["validation_days"]))
    labels = [tensor.labels[d] for d in val]
    for name, leg in [("hold", None), ("static", 0.0), *((f"static_legs_{leg:g}", leg) for leg in args.legs)]:
        print(json.dumps({"policy": name, "days": labels, **run(tensor, s.scenario, list(val), leg)}), flush=True)
    rotor = s.scenario.rotor
    v = s.scenario.d_max_m / s.scenario.slot_s
    print(json.dumps({"power_at_d_max_over_hover": round(rotor_power(v, rotor) / hover_power(rotor), 4),
                      "speed_mps": round(v, 2)}))


if __name__ == "__main__":
    main()
