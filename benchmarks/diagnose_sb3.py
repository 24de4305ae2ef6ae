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

from dswm import settings as S
from dswm.config import load_yaml
from dswm.pipeline.setup import build_controller, load_tensor, set_up
from dswm.protocol.evaluation import evaluate
from dswm.protocol.learning import learning_days
from dswm.settings import EvaluationSettings


def setup(root: Path, profile: str, method: str):
    """The evaluation set-up of the method's learning score job, the tensor and (training days, validation days)."""
    config = load_yaml(root / "config.yaml")
    config["profile"] = profile
    settings = S.resolve(config, root=root, schema=root / "workflow" / "schemas" / "config.schema.yaml")
    learning = S.learning_settings(config, profile)
    job = S.learning_score_slice(settings, learning, method)
    intensity = root / "results" / "calibration" / "demand_intensity.json"
    s = set_up(job, "evaluation", EvaluationSettings, intensity if intensity.exists() else None)
    tensor = load_tensor(root / "results" / "data" / learning.dataset)
    return s, tensor, learning_days(tensor, int(job["validation_days"])), learning.seed


def score(s, tensor, method: str, seed: int, path: Path, days: list[int], deterministic: bool) -> dict:
    """Served ratio and energy per slot of the model at ``path`` on ``days`` (as ``score_snapshot`` evaluates)."""
    ctrl = build_controller(s, method, seed)
    ctrl.load(path)
    ctrl.deterministic = deterministic
    ev = s.settings
    rows = evaluate(tensor=tensor, controller=ctrl, scenario=s.scenario, seed=seed, limits={"id": None, "ood": None},
                    profile=s.job["profile"], device=ev.device, batch_days=ev.batch_days, trajectory=False,
                    progress_interval_s=1e9, days={"validation": days}).days
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
