"""Why TD-MPC's planner does not learn on a workflow's data: its reward model's ranking of actions, and what the
planner and the policy prior do with it, on the learning curves' validation days.

Run (from a workflow root whose results/data/<dataset> and calibration exist, e.g. after `snakemake learning`):
    python benchmarks/diagnose_tdmpc.py [--profile demo] [--method tdmpc] MODEL.pt [MODEL.pt ...]
A MODEL is a learning run's model.pt or one of its snapshots (results/learning/milan/tdmpc/seed0/...).

Per model, on the validation days of `learning` (held out of the run, never a test day):
* ranking: along a trajectory of the pre-collection's heuristic (Lloyd moves plus its noise), every 12th slot,
  256 candidates from MPPI's initial Gaussian (N(0, max_std), clipped, projected) and 256 heuristic ones; the
  rank correlation of the model's predicted reward R(h(o), a) with the environment's one-step reward
  (``dswm.methods.tdmpc.diagnose``), and the true reward of the model's first choice against the candidates'
  mean and best;
* rollouts: the planner (MPPI, as at evaluation) and the policy prior pi alone, each acting on the validation days
  from the evaluation's initial fleet: served ratio, realized and predicted reward per slot, and the fleet's
  mean move (|mean over UAVs of (dx, dy)|, in D_max; near 0 for independent moves, 1 when the fleet flies as one)
  with its mean dx and dy.
"""
from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import numpy as np
import torch

from _learning_job import learning_job
from dswm.methods.collect import lloyd_moves
from dswm.methods.tdmpc.agent import project
from dswm.methods.tdmpc.diagnose import reward_ranking
from dswm.methods.tdmpc.planner import mppi
from dswm.pipeline.setup import build_controller
from dswm.protocol.learning import learning_days
from dswm.sim.core import core_from_tensor


def setup(root: Path, profile: str, method: str):
    """The method's learning-run controller (built as the learning_train job builds it), the validation core and
    the settings."""
    s, tensor, learning, job = learning_job(root, profile, method, "train")
    _, val = learning_days(tensor, int(job["validation_days"]))
    return (lambda: build_controller(s, method, learning.seed)), core_from_tensor(tensor, s.scenario, val), s


@torch.no_grad()
def ranking(model, core, settings, seed: int = 1) -> dict:
    rng, gen = np.random.default_rng(seed), torch.Generator().manual_seed(seed)
    k = core.scenario.n_uavs
    rows = {"gaussian": [], "heuristic": []}
    obs = core.reset(list(range(core.n_days)))
    for t in range(core.scenario.slots_per_day - 1):
        if t % 12 == 5:
            for b in range(core.n_days):
                one = {key: np.repeat(np.asarray(v)[b:b + 1], 256, 0) for key, v in obs.items()}
                cands = {"gaussian": project((settings.max_std * torch.randn(256, k, 3, generator=gen)).clamp(-1, 1)),
                         "heuristic": project(torch.as_tensor(lloyd_moves(one, core, rng, settings.precollect)))}
                for name, a in cands.items():
                    rows[name].append(reward_ranking(model, core, obs, b, a))
        obs = core.step(lloyd_moves(obs, core, rng, settings.precollect)).obs
    return {name: {f: round(float(np.mean([getattr(r, f) for r in rs])), 3) for f in ("spearman", "chosen", "mean",
                                                                                     "best")}
            for name, rs in rows.items()}


@torch.no_grad()
def rollout(model, core, settings, mode: str, seed: int = 0) -> dict:
    gen, k = torch.Generator().manual_seed(seed), core.scenario.n_uavs
    obs, prev = core.reset(list(range(core.n_days))), None
    sr, rew, pred, drift, dxy = [], [], [], [], []
    for _ in range(core.scenario.slots_per_day - 1):
        z = model.encode(*(torch.as_tensor(np.asarray(obs[key]), dtype=torch.float32)
                           for key in ("demand", "fleet", "time")))
        if mode == "policy":
            a = model.pi(z)
        else:
            res = mppi(model, z, cfg=settings.mppi(), generator=gen, prev_mean=prev)
            prev, a = res.mean, res.action
        a = project(a.reshape(-1, k, 3))
        pred.append(float(model.next(z, a.flatten(1))[1].mean()))
        out = core.step(a.numpy())
        obs = out.obs
        sr.append(float(out.sr.mean()))
        rew.append(float(out.reward.mean()))
        mean_move = a[..., :2].mean(1)                                        # (B, 2)
        drift.append(float(torch.linalg.vector_norm(mean_move, dim=-1).mean()))
        dxy.append(mean_move.mean(0).numpy())
    dx, dy = np.mean(dxy, 0)
    return {"served_ratio": round(float(np.mean(sr)), 3), "reward": round(float(np.mean(rew)), 3),
            "predicted_reward": round(float(np.mean(pred)), 3), "fleet_mean_move": round(float(np.mean(drift)), 3),
            "mean_dx": round(float(dx), 3), "mean_dy": round(float(dy), 3)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("models", nargs="+", type=Path)
    ap.add_argument("--root", type=Path, default=Path.cwd(), help="workflow root (config.yaml, results/data)")
    ap.add_argument("--profile", default="demo")
    ap.add_argument("--method", default="tdmpc")
    args = ap.parse_args()
    os.chdir(args.root)
    torch.set_num_threads(1)
    build, core, s = setup(args.root.resolve(), args.profile, args.method)
    for path in args.models:
        ctrl = build()
        ctrl.load(path)
        model, settings = ctrl.model, ctrl.settings
        out = {"model": str(path), "ranking": ranking(model, core, settings),
               **{mode: rollout(model, core, settings, mode) for mode in ("planner", "policy")}}
        print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
