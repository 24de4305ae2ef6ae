"""Training throughput of the learning baselines, and what SB3's VecEnv path costs against the bare core.

Run: python benchmarks/bench_rl.py [--methods ppo sac] [--rounds 2] [--repeats 5] [--threads 1]
Writes benchmarks/results/rl_cpu_t<threads>.json.

On the demo grid (20 x 20 cells, K = 16 of the config scenario, synthetic demand, ``bench_env.demo_core``):

* ``vec_env``: one day (143 slots) of uniform random actions for n_envs episodes, through ``FleetVecEnv.step``
  (flat actions in, flat observations out, the auto-reset at the day's end included) and through the bare
  ``FleetCore.step`` on the same batch; transitions per second of each and their ratio (goal: <= 3).
* one entry per learning method (:data:`ENTRIES`): ``fit`` of the method at its demo settings (config.yaml
  ``methods.<name>`` with ``budgets.demo`` when the section exists, else the entry's ``demo`` values) on a budget
  of ``--rounds`` rounds, timed whole (environment, updates, the checkpoint at the end); environment transitions
  per second and gradient steps per second from its manifest. An entry may change settings for the timing only
  (SAC starts updating at once: the steady state, not its random warm-up).

Every timing: one warm-up, then the median of ``--repeats`` (>= 5) with min and max (``_timing.timed``). A fit
of the full demo budget takes about ``demo transitions / transitions per second``.
"""
from __future__ import annotations

import argparse
import dataclasses
import tempfile
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from _timing import rate, timed, write
from bench_env import demo_core
from dswm.config import load_yaml, to_plain
from dswm.methods.registry import load_class
from dswm.pipeline.setup import prepare_process

ROOT = Path(__file__).resolve().parents[1]


def sb3_budget(options, rounds: int) -> dict:
    """An SB3 learner's budget of ``rounds`` rounds, one checkpoint at the end."""
    return {"day_episodes": options.n_envs * rounds, "checkpoint_every": rounds}


@dataclasses.dataclass(frozen=True)
class Entry:
    """One learning method in the benchmark."""

    target: str
    """Its controller class, "package.module:ClassName"."""
    budget: Callable[[Any, int], dict]
    """Settings that make a budget of n rounds (the method's own budget keys)."""
    demo: dict
    """Its demo settings, used while config.yaml has no ``methods.<name>`` section."""
    timing: dict = dataclasses.field(default_factory=dict)
    """Settings changed for the timing only."""


ENTRIES: dict[str, Entry] = {
    "ppo": Entry(target="dswm.methods.rl.sb3:PPOController", budget=sb3_budget, demo={
        "n_envs": 8, "day_episodes": 560, "net_arch": [128, 128], "learning_rate": 3.0e-4, "gamma": 0.99,
        "batch_size": 286, "checkpoint_every": 10, "n_epochs": 5, "gae_lambda": 0.95, "clip_range": 0.2,
        "ent_coef": 0.0, "vf_coef": 0.5, "max_grad_norm": 0.5, "log_std_init": -0.5}),
    "sac": Entry(target="dswm.methods.rl.sb3:SACController", budget=sb3_budget, timing={"learning_starts": 0}, demo={
        "n_envs": 4, "day_episodes": 40, "net_arch": [128, 128], "learning_rate": 3.0e-4, "gamma": 0.99,
        "batch_size": 128, "checkpoint_every": 5, "buffer_size": 6000, "learning_starts": 572, "tau": 0.005,
        "train_freq": 1, "gradient_steps": 1, "ent_coef_init": 0.1, "auto_entropy": True,
        "matmul_dtype": "bfloat16"}),
    "maddpg": Entry(target="dswm.methods.maddpg:MADDPGController", budget=lambda o, rounds: maddpg_budget(o, rounds),
                    demo={}, timing={"warmup": 143}),
    "tdmpc": Entry(target="dswm.methods.tdmpc:TDMPCController", budget=lambda o, rounds: tdmpc_budget(o, rounds),
                   demo={}),
}


def maddpg_budget(options, rounds: int) -> dict:
    """MADDPG on ``rounds`` x 4 day-episodes (one at random: ``timing``), one checkpoint at the end."""
    return {"transitions": 143 * 4 * rounds, "checkpoint_every": 4 * rounds}


def tdmpc_budget(options, rounds: int) -> dict:
    """TD-MPC's pre-collection and seed steps, then ``rounds`` rounds of ``parallel`` own day-episodes with the
    demo's gradient steps per own episode (2 rounds are its whole demo budget)."""
    per_episode = (options.steps - options.seed_steps) // max(options.episodes, 1)
    episodes = options.parallel * rounds
    return {"episodes": episodes, "steps": options.seed_steps + per_episode * episodes,
            "checkpoint_every": options.steps}


def demo_options(name: str, entry: Entry):
    """(class, demo options, where they came from)."""
    cls = load_class(entry.target, key=f"bench_rl:{name}")
    config = load_yaml(ROOT / "config.yaml")
    if name in config.get("methods", {}):
        return cls, cls.options_from_config(name=name, config=config, profile="demo"), "config.yaml (demo)"
    return cls, cls.options_from_plain(name=name, data=entry.demo), "bench_rl.py ENTRIES (demo)"


def bench_fit(name: str, entry: Entry, core, *, rounds: int, repeats: int) -> dict:
    """Whole ``fit`` timings of one method on ``rounds`` rounds at its demo settings."""
    cls, options, source = demo_options(name, entry)
    plain = {**to_plain(options), **entry.timing, **entry.budget(options, rounds)}
    timed_options = cls.options_from_plain(name=name, data=plain)
    manifests = []

    def run():
        with tempfile.TemporaryDirectory() as run_dir:
            ctl = cls(name=name, seed=0, device="cpu", options=timed_options)
            manifests.append(ctl.fit(core, run_dir=run_dir))

    timing = timed(run, repeats=repeats)
    m = manifests[-1]
    return {"settings_source": source, "timing_changes": {**entry.timing, **entry.budget(options, rounds)},
            "demo_settings": to_plain(options), "n_transitions": m["n_transitions"], "gradient_steps": m["steps"],
            "seconds": timing, "transitions_per_second": rate(timing, m["n_transitions"]),
            "gradient_steps_per_second": rate(timing, m["steps"])}


def bench_vec_env(core, n_envs: int, *, repeats: int) -> dict:
    """One day of random actions through SB3's VecEnv path and through the bare core, same batch."""
    from dswm.methods.rl.vec_env import FleetVecEnv

    scenario = core.scenario
    slots, k = scenario.slots_per_day - 1, scenario.n_uavs
    actions = np.random.default_rng(0).uniform(-1, 1, (slots, n_envs, 3 * k)).astype(np.float32)
    venv = FleetVecEnv(core, n_envs=n_envs, seed=0)
    days = np.arange(n_envs) % core.n_days

    def vec_day():
        for a in actions:
            venv.step(a)

    def core_day():
        for a in actions:
            core.step(a.reshape(n_envs, k, 3))

    vec = timed(vec_day, setup=venv.reset, repeats=repeats)
    bare = timed(core_day, setup=lambda: core.reset(days), repeats=repeats)
    work = n_envs * slots
    return {"n_envs": n_envs, "slots": slots, "vec_env_seconds": vec, "core_seconds": bare,
            "vec_env_transitions_per_second": rate(vec, work), "core_transitions_per_second": rate(bare, work),
            "slowdown_median": vec["median_s"] / bare["median_s"], "goal_max_slowdown": 3.0}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--methods", nargs="+", default=list(ENTRIES), choices=list(ENTRIES))
    ap.add_argument("--rounds", type=int, default=2, help="rounds of n_envs day-episodes per timed fit")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--name", default=None, help="result name (default rl_cpu_t<threads>)")
    args = ap.parse_args()
    prepare_process(args.threads)   # as every job does (dswm.pipeline.setup.init_process)
    core = demo_core(days=16)
    n_envs = getattr(demo_options(args.methods[0], ENTRIES[args.methods[0]])[1], "n_envs", 8)
    result = {"grid": [core.grid.rows, core.grid.cols], "n_uavs": core.scenario.n_uavs, "rounds": args.rounds,
              "vec_env": bench_vec_env(core, n_envs, repeats=args.repeats),
              "methods": {name: bench_fit(name, ENTRIES[name], core, rounds=args.rounds, repeats=args.repeats)
                          for name in args.methods}}
    write(args.name or f"rl_cpu_t{args.threads}", result)


if __name__ == "__main__":
    main()
