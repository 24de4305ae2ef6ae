"""What an SB3 learner (PPO, SAC) learned: its policy's mean, which every evaluation scores, against its sampled
actions, which its training return measures, on the learning curves' validation days and on days it trained on.

Run (from a workflow root whose results/data/<dataset> and calibration exist, e.g. after `snakemake learning`):
    python benchmarks/diagnose_sb3.py [--profile demo] [--method ppo] [--train-days 3] MODEL.pt [MODEL.pt ...]
A MODEL is a learning run's model.pt or one of its snapshots (results/learning/milan/ppo/seed0/snapshots/...).

Per model, one JSON line: the served ratio and energy per slot on the validation days of `learning` (held out of
the run, never a test day) and on the first ``--train-days`` of the days the run trained on, each with the
policy's mean (``deterministic``, as the evaluation acts) and with its sampled actions (``stochastic``, as
training acts), in the evaluation's own environment and initial fleet, seeded as the evaluation seeds.
A training return that rises while the deterministic score does not is then told apart: the sampled policy
improving against its own noise, or a gap between the days it trained on and held-out days.
"""
from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import torch

from _learning_job import learning_job
from dswm.pipeline.setup import score_snapshot
from dswm.protocol.learning import learning_days


def setup(root: Path, profile: str, method: str):
    """The evaluation set-up of the method's learning score job, the tensor and (training days, validation days)."""
    s, tensor, learning, job = learning_job(root, profile, method, "score")
    return s, tensor, learning_days(tensor, int(job["validation_days"])), learning.seed


def score(s, tensor, method: str, seed: int, path: Path, days: list[int], deterministic: bool) -> dict:
    """Served ratio and energy per slot of the model at ``path`` on ``days``, scored as the learning_score job scores
    a snapshot, acting with the policy's mean (``deterministic``) or its samples."""
    rows = score_snapshot(s, tensor=tensor, method=method, seed=seed, path=path, days={"validation": days},
                          progress_interval_s=1e9, configure=lambda ctrl: setattr(ctrl, "deterministic", deterministic))
    return {"served_ratio": round(float(rows["sr_mean"].mean()), 4),
            "energy_kj_per_slot": round(float(rows["energy_kj_per_slot"].mean()), 1)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("models", nargs="+", type=Path)
    ap.add_argument("--root", type=Path, default=Path.cwd(), help="workflow root (config.yaml, results/data)")
    ap.add_argument("--profile", default="demo")
    ap.add_argument("--method", default="ppo", help="an SB3 learner of config.yaml (ppo, sac)")
    ap.add_argument("--train-days", type=int, default=3, help="how many of the run's training days to score")
    args = ap.parse_args()
    os.chdir(args.root)
    torch.set_num_threads(1)
    s, tensor, (fit, val), seed = setup(args.root.resolve(), args.profile, args.method)
    sets = {"validation": val, "training": fit[:args.train_days]}
    for path in args.models:
        out = {"model": str(path), "days": {k: [tensor.labels[d] for d in v] for k, v in sets.items()}}
        for name, days in sets.items():
            out[name] = {mode: score(s, tensor, args.method, seed, path, days, mode == "deterministic")
                         for mode in ("deterministic", "stochastic")}
        print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
