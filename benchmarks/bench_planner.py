"""DSWM planning per slot and world-model training throughput.

Run: python benchmarks/bench_planner.py [--threads 2] [--device cpu] [--slots 8]
Writes benchmarks/results/planner_<device>_t<threads>.json and .png.

Per-slot planning of DSWM+'s planner (``dswm_plus``) is timed at the paper's production settings (N_cem=512,
6 iterations, H=15, E=5, K=16, G=400 on a 20x20 grid), with its proposal and continuation and without them
(plain CEM), and at the demo and smoke planner sizes of config.yaml, where Algorithm 1 (``dswm``) is timed too; the paper profile runs the imagined steps compiled
(``planner.compile``), and the same production planner is also timed eager. One imagined step is broken
down into its eager parts (RSSM prior, demand ensemble + anchoring, fleet kinematics, service physics), and
the model's compiled share of it times the 90 imagined steps of a production slot is recorded as a floor under
planning time that no change to the physics, the association or the proposal can go below.
Training throughput is gradient steps per second at the configured batch and sequence length. Target on a
2-core machine: <= 300 ms per slot. Weights are untrained: the cost does not depend on their values. The
machine's load average is recorded;
on a shared machine under load, two torch threads can be many times slower than one (OpenMP contention),
so compare --threads 1 and 2.
"""
from __future__ import annotations

import argparse
import copy
import statistics
import time

import numpy as np
import torch
import yaml

from _timing import RESULTS, spread_ms, write
from dswm.pipeline.setup import prepare_process
from dswm.methods.dswm.agent import DSWMController
from dswm.methods.dswm.settings import resolve as dswm_settings
from dswm.methods.search import configured_search
from dswm.sim.scenario import load_scenario
from dswm.methods.base import DayContext
from dswm.sim.core import FleetCore, Grid, initial_positions
from dswm.sim.env import synthetic_demand
from dswm.sim.fleet import available, fleet_step
from dswm.sim.physics import service
from dswm.methods.dswm.planner import anchor
from dswm.methods.collect import collect
from dswm.methods.dswm.training import make_optimizer


def _controller(cfg: dict, profile: str, planner_over: dict, core: FleetCore, device: str,
                method: str = "dswm_plus") -> DSWMController:
    c = copy.deepcopy(cfg["dswm"])
    c["device"] = device
    c["methods"][method] = {**(c["methods"].get(method) or {}),
                            "planner": {**((c["methods"].get(method) or {}).get("planner") or {}), **planner_over}}
    ctl = DSWMController(name=method, seed=0, device=device,
                         options=dswm_settings(c, method=method, profile=profile,
                                               search=configured_search(cfg, profile)[0]))
    ctl.model = ctl._build_model(core.grid, core.scenario)
    ctl.model.set_normalizer(torch.as_tensor(core.demand[:1].cpu().numpy()))
    ctl.model.eval()
    return ctl


def _time_slots(ctl: DSWMController, core: FleetCore, slots: int) -> dict:
    """Median and spread of per-slot planning time over ``slots`` consecutive slots of one day."""
    obs = core.reset([0])
    ctl.reset(DayContext(dataset="bench", day=0, label="d0", split="id", grid=core.grid, scenario=core.scenario,
                         geometry=core.geom, cells=core.cells, init_pos=core.init_pos.cpu().numpy(),
                         device=str(ctl.device)))
    times = []
    for _ in range(slots + 1):
        t0 = time.perf_counter()
        a = ctl.act({k: v[0] for k, v in obs.items()})
        times.append(1e3 * (time.perf_counter() - t0))
        obs = core.step(a[None]).obs
    first, times = times[0], times[1:]                     # the first slot pays one-time allocations (and compiling)
    return {"median_ms": round(statistics.median(times), 1), "min_ms": round(min(times), 1),
            "max_ms": round(max(times), 1), "first_slot_ms": round(first, 1)}


def _step_inputs(ctl: DSWMController, core: FleetCore, n: int) -> tuple:
    """(RSSM state, random actions (n, K, 3), fleet, observed map x_now) of one imagined step of n candidates."""
    dev = ctl.device
    state = ctl.model.rssm.initial(n, device=dev)
    act = torch.rand(n, core.scenario.n_uavs, 3, device=dev) * 2 - 1
    fleet = type(core.state)(*(t[0].to(dev) for t in core.state)).expand(n)
    return state, act, fleet, core.demand[0, 0].to(dev)


def _breakdown(ctl: DSWMController, core: FleetCore, n: int) -> dict:
    """Milliseconds of each part of ONE imagined step for n candidates."""
    model, dev = ctl.model, ctl.device
    state, act, fleet, x_now = _step_inputs(ctl, core, n)
    with torch.inference_mode():
        feat = model.rssm.feat(model.rssm.img_step(state, act.flatten(1), sample=False))
        nxt, _ = fleet_step(fleet, act, core.geom, core.scenario)
        x_hat, _ = anchor(x_now, model.demand_members(feat), 0.95)
        avail = available(nxt)
        cells = core.cells.to(dev)
        parts = {
            "rssm_prior": spread_ms(lambda: model.rssm.img_step(state, act.flatten(1), sample=False), reps=10),
            "demand_ensemble_and_anchor": spread_ms(lambda: anchor(x_now, model.demand_members(feat), 0.95),
                                                    reps=10),
            "fleet_step": spread_ms(lambda: fleet_step(fleet, act, core.geom, core.scenario), reps=10),
            "service_physics": spread_ms(lambda: service(x_hat, nxt.pos, avail, cells, params=core.params,
                                                         bw_logit=act[..., 2]), reps=10),
        }
    return {key: round(v["median_ms"], 2) for key, v in parts.items()} | {"spread_ms": parts}


def _model_floor(ctl: DSWMController, core: FleetCore, n: int, steps: int) -> dict:
    """A floor under per-slot planning: the model's share of ONE imagined step, compiled as the paper profile
    compiles it (RSSM prior, demand ensemble and anchoring, fleet kinematics; no service physics, association,
    continuation, CEM bookkeeping or proposal), times the ``steps`` imagined steps of a slot."""
    model = ctl.model
    state, act, fleet, x_now = _step_inputs(ctl, core, n)

    def model_part(state, fleet, act):
        nxt, _ = fleet_step(fleet, act, core.geom, core.scenario)
        feat = model.rssm.feat(model.rssm.img_step(state, act.flatten(1), sample=False))
        return nxt, anchor(x_now, model.demand_members(feat), 0.95)

    compiled = torch.compile(model_part, dynamic=False, fullgraph=True)
    with torch.inference_mode():
        spread = spread_ms(lambda: compiled(state, fleet, act), reps=20)
    ms = spread["median_ms"]
    return {"ms_per_imagined_step": round(ms, 2), "imagined_steps_per_slot": steps,
            "ms_per_slot": round(ms * steps, 1), "spread_ms_per_imagined_step": spread}


def _train_throughput(cfg: dict, core: FleetCore, device: str, steps: int) -> dict:
    s = dswm_settings(cfg["dswm"], method="dswm", profile="demo", search=configured_search(cfg, "demo")[0])
    rep = collect(core, n_transitions=2 * 143, cfg=s.training, seed=0, day_ids=np.arange(core.n_days))
    ctl = DSWMController(name="dswm", seed=0, device=device, options=s)
    model = ctl._build_model(core.grid, core.scenario)
    model.set_normalizer(rep.demand)
    opt = make_optimizer(model, s.training)
    gen = torch.Generator().manual_seed(0)

    def step():
        batch = {k: v.to(device) for k, v in rep.sample(s.training.batch, s.training.seq_len, gen).items()}
        loss, _ = model.loss(batch)
        opt.zero_grad()
        loss.backward()
        opt.step()
        model.update_teacher()

    spread = spread_ms(step, reps=max(steps, 5), warmup=2)
    ms = spread["median_ms"]
    return {"batch": s.training.batch, "seq_len": s.training.seq_len, "median_ms_per_step": round(ms, 1),
            "steps_per_s": round(1e3 / ms, 2), "spread_ms_per_step": spread}


def _figure(result: dict, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8))
    names = list(result["per_slot"])
    vals = [result["per_slot"][n]["median_ms"] for n in names]
    axes[0].barh(names, vals, color="tab:blue")
    axes[0].axvline(300, color="tab:red", ls="--", label="target 300 ms")
    floor = result["model_only_floor_compiled"]["ms_per_slot"]
    axes[0].axvline(floor, color="tab:green", ls=":", label=f"model-only floor {floor:.0f} ms")
    axes[0].set_xlabel("median planning time per slot (ms)")
    axes[0].set_xscale("log")
    axes[0].legend(fontsize=8)
    axes[0].set_title(f"per-slot planning ({result['device']}, load {result['load_avg_1min_start']:.1f})")
    parts = result["imagined_step_breakdown_ms"]
    axes[1].bar(list(parts), list(parts.values()), color="tab:gray")
    axes[1].set_ylabel("ms per imagined step (N=512)")
    axes[1].set_title(f"one imagined step; training {result['training']['steps_per_s']} steps/s")
    axes[1].tick_params(axis="x", labelrotation=20, labelsize=8)
    fig.tight_layout()
    tmp = path.with_name(f".{path.stem}.tmp.png")
    fig.savefig(tmp, dpi=120)
    tmp.replace(path)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--slots", type=int, default=8, help="timed slots per setting")
    ap.add_argument("--train-steps", type=int, default=20)
    args = ap.parse_args()
    prepare_process(args.threads)   # as every job does (dswm.pipeline.setup.init_process)
    load0 = __import__("os").getloadavg()[0]
    cfg = yaml.safe_load((RESULTS.parents[1] / "config.yaml").read_text())
    scenario = load_scenario(RESULTS.parents[1] / "config.yaml", standin=True)  # u: the demo calibration
    grid = Grid(rows=20, cols=20, cell_m=235.0)
    demand = synthetic_demand(days=2, rows=20, cols=20, slots=scenario.slots_per_day, seed=0) + 0.02
    core = FleetCore(demand=demand, grid=grid, scenario=scenario, dataset="bench", day_labels=["d0", "d1"],
                     init_pos=initial_positions(demand.mean((0, 1)), grid, scenario.n_uavs, 0), device=args.device)
    production = {"n_samples": 512, "n_elites": 64, "iterations": 6, "horizon": 15}
    settings_list = {  # DSWM+'s planner (dswm_plus) unless named; Algorithm 1 is dswm's
        "production (configured proposal)": ("paper", production),
        "production, eager (compile off)": ("paper", {**production, "compile": False}),
        "production, plain CEM": ("paper", {**production, "proposal": "none", "continuation": "hold"}),
        "demo sizes": ("demo", {}),
        "demo sizes, Algorithm 1 (dswm)": ("demo", {"method": "dswm"}),
        "smoke sizes": ("smoke", {}),
    }
    per_slot = {}
    for name, (profile, over) in settings_list.items():
        over = dict(over)
        ctl = _controller(cfg, profile, over, core, args.device, method=over.pop("method", "dswm_plus"))
        per_slot[name] = {**_time_slots(ctl, core, args.slots),
                          "planner": {k: getattr(ctl.settings.planner, k) for k in
                                      ("n_samples", "n_elites", "iterations", "horizon", "proposal", "continuation",
                                       "compile")}}
        print(name, per_slot[name], flush=True)
    ctl = _controller(cfg, "paper", production, core, args.device)
    result = {"device": args.device, "threads": args.threads, "load_avg_1min_start": load0,
              "grid": [20, 20], "K": scenario.n_uavs, "E": ctl.settings.world_model.ensemble,
              "per_slot": per_slot, "imagined_step_breakdown_ms": _breakdown(ctl, core, 512),
              "model_only_floor_compiled": _model_floor(ctl, core, 512,
                                                        production["iterations"] * production["horizon"]),
              "training": _train_throughput(cfg, core, args.device, args.train_steps),
              "target_ms_per_slot": 300}
    name = f"planner_{args.device.split(':')[0]}_t{args.threads}"
    write(name, result)
    _figure(result, RESULTS / f"{name}.png")


if __name__ == "__main__":
    main()
