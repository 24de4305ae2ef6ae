"""Why EMORL-TCTO's learning curve stays flat: what its PPO tasks did to their parents, and how much training the
executed archive member has behind it.

Run (from a workflow root after `snakemake learning`, or any EMORL-TCTO train job's checkpoint):
    python benchmarks/diagnose_emorl.py [--profile demo] [--checkpoint PATH]

EMORL-TCTO (``dswm.methods.emorl_tcto``) trains a population of PPO policies: a warm-up run per starting policy, then
tasks that continue an archive member (its parent) with PPO on a weighted objective for ``task_rounds`` rounds. A
child enters the archive only where it is not dominated on the measured training days, and the member that
``select_rule`` names is executed (in config.yaml the one serving best there). The checkpoint keeps every task as
(parent id, weight, child minus parent objectives) and every member's parent, so this script reads, without
simulating:
* how many tasks raised or lowered their parent's served ratio (all tasks, and those weighting served ratio alone);
* the depth of every lineage (tasks from an untrained policy) and the executed member's depth, rounds and PPO
  transitions, against the run's total.
One JSON object on standard output. The round counts and the executed member's rule (``select_rule``) come from
the settings of the learning run's score job (``--profile``).
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from _learning_job import learning_job
from dswm.methods.emorl_tcto.archive import select_member

SERVED_RATIO = 0  # index of the served ratio in the objective vectors (dswm.methods.emorl_tcto.objectives)


def lineage(members: dict, member: int) -> list[int]:
    """``member`` and its ancestors up to an untrained policy (parent None), newest first."""
    out = [member]
    while members[out[-1]]["parent"] is not None:
        out.append(members[out[-1]]["parent"])
    return out


def summarize(blob: dict, *, warmup_rounds: int, task_rounds: int, transitions_per_round: int, rule: str,
              weight=None) -> dict:
    """The numbers of the module docstring from a checkpoint's ``blob``. The executed member is the one that
    ``select_member`` picks with ``rule`` and ``weight`` (``select_rule``, ``select_weight``), as the controller
    picks it."""
    members, tasks, archive = blob["members"], blob["tasks"], [int(i) for i in blob["archive"]]
    untrained = [i for i, m in members.items() if m["parent"] is None]
    deltas = np.array([np.asarray(d, dtype=float)[SERVED_RATIO] for _, _, d in tasks])
    weights = np.array([np.asarray(w, dtype=float) for _, w, _ in tasks])
    n_warm = len(untrained)       # the first tasks: one warm-up run from each untrained policy
    later, later_w = deltas[n_warm:], weights[n_warm:]
    alone = np.all(later_w == np.eye(later_w.shape[1])[SERVED_RATIO], axis=1)
    executed = archive[select_member(np.array([members[i]["objectives"] for i in archive]), rule, weight)]
    chain = lineage(members, executed)
    rounds = warmup_rounds + task_rounds * (len(chain) - 2)      # chain: the member ... its warm-up, untrained
    return {
        "tasks": len(tasks), "warmup_tasks": n_warm,
        "warmup_sr_deltas": [round(float(d), 4) for d in deltas[:n_warm]],
        "later_tasks": int(later.size), "later_lowered": int((later < 0).sum()),
        "later_sr_delta_mean": round(float(later.mean()), 4),
        "served_ratio_alone_tasks": int(alone.sum()), "served_ratio_alone_lowered": int((later[alone] < 0).sum()),
        "untrained_sr": [round(float(members[i]["objectives"][SERVED_RATIO]), 4) for i in untrained],
        "deepest_lineage_tasks": max(len(lineage(members, i)) - 1 for i in members),
        "archive": archive, "executed_member": executed,
        "executed_sr": round(float(members[executed]["objectives"][SERVED_RATIO]), 4),
        "executed_lineage": chain, "executed_rounds": rounds,
        "executed_transitions": rounds * transitions_per_round,
        "run_transitions": int(blob["num_timesteps"]),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--root", type=Path, default=Path("."), help="the workflow root (config.yaml, results/)")
    ap.add_argument("--profile", default="demo", help="the profile the learning run ran under")
    ap.add_argument("--checkpoint", type=Path, default=None,
                    help="default: the learning run's results/learning/<dataset>/emorl_tcto/seed<seed>/train/"
                         "checkpoint.pt")
    args = ap.parse_args()
    root = args.root.resolve()
    s, _, learning, _ = learning_job(root, args.profile, "emorl_tcto", "score")
    o = s.method.options
    path = args.checkpoint or (root / "results" / "learning" / learning.dataset / "emorl_tcto"
                               / f"seed{learning.seed}" / "train" / "checkpoint.pt")
    if not path.is_file():
        raise SystemExit(f"{path}: no EMORL-TCTO checkpoint; run `snakemake --cores 2 learning` first")
    blob = torch.load(path, map_location="cpu", weights_only=False)
    days = s.scenario.slots_per_day - 1
    out = summarize(blob, warmup_rounds=o.warmup_rounds, task_rounds=o.task_rounds,
                    transitions_per_round=o.n_envs * days, rule=o.select_rule, weight=o.select_weight)
    print(json.dumps({"checkpoint": str(path), **out}))


if __name__ == "__main__":
    main()
