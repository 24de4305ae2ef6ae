"""HRL-TPRA: the batched per-UAV actors against the per-actor loop, the serial pointer decoding, a training round
and acting, on one thread.

Run: python benchmarks/bench_hrl_tpra.py [--repeats 5] [--threads 1] [--rounds 2]
Writes benchmarks/results/hrl_tpra_cpu_t<threads>.json.

* ``actors``: the K = 16 resource actors (input ``features.local_dim(crop_radius)``, the demo's hidden layers, 3
  outputs) and the K critics, as ONE stacked network (``actors.StackedMLP``: (K, in, out) parameters, one
  ``baddbmm`` per layer) and as 16 separate ``nn.Module``s called in a Python loop (``actors.LoopMLP`` with the
  same weights), at batch sizes of acting (3 evaluated days, the n_envs = 8 training days of a round) and of
  training (a 286 day-slot minibatch, a whole 1144 day-slot round); forward alone and forward + backward
  (the sum of squares of the outputs); the loop's median over the stacked median is the speed-up.
* ``pointer``: one greedy decoding of 3 days (acting) and one teacher-forced forward + backward of a 48-decision
  minibatch (training), K = 16 serial steps over N candidates.
* ``fit``: ``fit`` at the demo settings (config.yaml ``methods.hrl_tpra`` with ``budgets.demo`` when the section
  exists, else :data:`DEMO`) on ``--rounds`` rounds of n_envs days of the 20 x 20, K = 16 benchmark core
  (``bench_env.demo_core``), timed whole; seconds per round, and the demo's whole fit estimated from it.
* ``act``: ``act_batch`` on 3 days at once, a whole day of 143 slots (planning at every macro-slot start
  included), in ms per slot.

Every timing: warm-up calls first, then the median of the repeats with min and max (``_timing``).
"""
from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import numpy as np
import torch

from _timing import spread_ms, timed, write
from bench_env import demo_core
from dswm.config import load_yaml, to_plain
from dswm.methods.base import DayContext
from dswm.methods.hrl_tpra import HRLTPRAController, HRLTPRASettings
from dswm.methods.hrl_tpra.actors import LoopMLP, StackedMLP
from dswm.methods.hrl_tpra.features import GLOBAL_FEATURES, Frame, local_dim, plan_inputs
from dswm.methods.hrl_tpra.pointer import PointerPlanner
from dswm.pipeline.setup import prepare_process

ROOT = Path(__file__).resolve().parents[1]
DEMO = {"macro_slots": 6, "candidates": 32, "pointer_hidden": 64, "tanh_clip": 10.0, "crop_radius": 2,
        "actor_hidden": 64, "actor_depth": 2, "fine_scale": 0.5, "log_std_init": -0.5, "gamma": 0.95,
        "gae_lambda": 0.95, "high_gamma": 0.5, "clip_range": 0.2, "ent_coef": 0.0, "high_ent_coef": 0.01,
        "lr": 3.0e-4, "high_lr": 3.0e-4, "max_grad_norm": 0.5, "n_envs": 8, "day_episodes": 384, "n_epochs": 5,
        "high_epochs": 2, "batch_size": 286, "high_batch_size": 48, "log_points": 200, "checkpoint_every": 8}
"""The demo settings, used while config.yaml has no ``methods.hrl_tpra`` section."""
ACT_BATCHES = (3, 8)
TRAIN_BATCHES = (286, 1144)


def demo_options() -> tuple[HRLTPRASettings, str]:
    config = load_yaml(ROOT / "config.yaml")
    if "hrl_tpra" in config.get("methods", {}):
        return (HRLTPRAController.options_from_config(name="hrl_tpra", config=config, profile="demo"),
                "config.yaml (demo)")
    return HRLTPRAController.options_from_plain(name="hrl_tpra", data=DEMO), "bench_hrl_tpra.py DEMO"


def bench_pair(stacked: StackedMLP, n: int, *, reps: int) -> dict:
    """Forward and forward + backward of the stacked network and of the loop of modules on (K, n, in) inputs."""
    loop = LoopMLP.from_stacked(stacked)
    x = torch.randn(stacked.n, n, stacked.sizes[0])
    with torch.no_grad():
        diff = float((stacked(x) - loop(x)).abs().max())

    def fwd(net):
        def run():
            with torch.no_grad():
                net(x)
        return run

    def fwd_bwd(net):
        def run():
            net.zero_grad(set_to_none=True)
            net(x).pow(2).sum().backward()
        return run

    out = {"batch": n, "max_abs_difference": diff}
    for mode, make in (("forward", fwd), ("forward_backward", fwd_bwd)):
        s, lp = spread_ms(make(stacked), reps=reps, warmup=5), spread_ms(make(loop), reps=reps, warmup=5)
        out[mode] = {"stacked": s, "loop": lp, "speedup_median": round(lp["median_ms"] / s["median_ms"], 2)}
    return out


def bench_actors(options: HRLTPRASettings, k: int, *, reps: int) -> dict:
    torch.manual_seed(0)
    d, h = local_dim(options.crop_radius), [options.actor_hidden] * options.actor_depth
    nets = {"actor": StackedMLP(n=k, sizes=[d, *h, 3], out_gain=0.01),
            "critic": StackedMLP(n=k, sizes=[d + len(GLOBAL_FEATURES), *h, 1])}
    return {name: {"sizes": net.sizes, "acting": [bench_pair(net, n, reps=reps) for n in ACT_BATCHES],
                   "training": [bench_pair(net, n, reps=reps) for n in TRAIN_BATCHES]} for name, net in nets.items()}


def bench_pointer(options: HRLTPRASettings, core, *, reps: int) -> dict:
    torch.manual_seed(0)
    planner = PointerPlanner(n_uavs=core.scenario.n_uavs, hidden=options.pointer_hidden, tanh_clip=options.tanh_clip)
    frame = Frame.of(core.grid, core.scenario)
    obs = core.reset(np.arange(48) % core.n_days)
    plan = plan_inputs(*(torch.as_tensor(obs[k]) for k in ("demand", "fleet", "time")), frame, options.candidates)

    def act():
        with torch.no_grad():
            planner(plan.cand[:3], plan.uav[:3], plan.dist[:3], greedy=True)

    choice = planner(plan.cand, plan.uav, plan.dist, greedy=True).choice

    def train():
        planner.zero_grad(set_to_none=True)
        planner(plan.cand, plan.uav, plan.dist, choice=choice).logp.sum().backward()

    return {"steps": core.scenario.n_uavs, "candidates": options.candidates,
            "greedy_decode_3_days": spread_ms(act, reps=reps, warmup=5),
            "teacher_forced_forward_backward_48": spread_ms(train, reps=reps, warmup=3)}


def bench_fit(options: HRLTPRASettings, source: str, core, *, rounds: int, repeats: int) -> tuple[dict, object]:
    plain = {**to_plain(options), "day_episodes": options.n_envs * rounds, "checkpoint_every": rounds}
    timed_options = HRLTPRAController.options_from_plain(name="hrl_tpra", data=plain)
    fitted = []

    def run():
        with tempfile.TemporaryDirectory() as run_dir:
            ctl = HRLTPRAController(name="hrl_tpra", seed=0, options=timed_options)
            fitted.append((ctl, ctl.fit(core, run_dir=run_dir)))

    timing = timed(run, repeats=repeats)
    ctl, manifest = fitted[-1]
    per_round = timing["median_s"] / rounds
    demo_rounds = options.day_episodes // options.n_envs
    return {"settings_source": source, "demo_settings": to_plain(options), "rounds": rounds,
            "n_transitions": manifest["n_transitions"], "gradient_steps": manifest["steps"], "seconds": timing,
            "seconds_per_round_median": per_round, "demo_rounds": demo_rounds,
            "demo_fit_seconds_estimate": per_round * demo_rounds}, ctl


def bench_act(ctl: HRLTPRAController, core, *, repeats: int) -> dict:
    days = [0, 1, 2]
    ctxs = [DayContext(dataset="bench", day=d, label=core.day_labels[d], split="id", grid=core.grid,
                       scenario=core.scenario, geometry=core.geom, cells=core.cells, init_pos=core.init_pos.numpy())
            for d in days]
    obs, seq = core.reset(days), []
    ctl.reset_batch(ctxs)
    for _ in range(core.scenario.slots_per_day - 1):  # the day's observations under the policy, recorded once
        seq.append(obs)
        obs = core.step(ctl.act_batch(obs)).obs

    def day():
        for o in seq:
            ctl.act_batch(o)

    timing = timed(day, setup=lambda: ctl.reset_batch(ctxs), repeats=repeats)
    return {"days": len(days), "slots": len(seq), "seconds_per_day": timing,
            "ms_per_slot_median": 1e3 * timing["median_s"] / len(seq)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--rounds", type=int, default=2, help="rounds of n_envs day-episodes per timed fit")
    args = ap.parse_args()
    prepare_process(args.threads)   # as every job does (dswm.pipeline.setup.init_process)
    options, source = demo_options()
    core = demo_core(days=16)
    core.day_ids = np.arange(core.n_days)
    reps = max(30, args.repeats)
    fit, ctl = bench_fit(options, source, core, rounds=args.rounds, repeats=args.repeats)
    result = {"grid": [core.grid.rows, core.grid.cols], "n_uavs": core.scenario.n_uavs,
              "actors": bench_actors(options, core.scenario.n_uavs, reps=reps),
              "pointer": bench_pointer(options, core, reps=reps), "fit": fit,
              "act": bench_act(ctl, core, repeats=args.repeats)}
    write(f"hrl_tpra_cpu_t{args.threads}", result)


if __name__ == "__main__":
    main()
