"""How far each learner's training can speed up at all: the time of its matrix products against its whole time.

Run: python benchmarks/gemm_ceiling.py --rates benchmarks/results/learners_cpu_t1.json [--rates more.json]
         [--items sac maddpg tdmpc dswm_world_model] [--out benchmarks/results/gemm_ceiling_cpu_t1.json]

Every paper setting fixes the networks, batches and epochs, so it fixes the matrix products (GEMMs and
convolutions) of a training unit, and they already run in bfloat16 where the paper profile says so. Their time
is the floor under any speed-up that leaves the settings as they are (short of fewer or cheaper products): the
ceiling of the speed-up over the baseline is the baseline's seconds per repeat over the current GEMM seconds per
repeat, and the time left for everything else at the 3x goal is a third of the baseline's repeat minus those
GEMM seconds (negative: the goal needs the products themselves faster).

For each item, in its own one-thread process on the current tree (``bench_learners.measure_item``, the same probe
and the same units as ``bench_learners.py``), every unit of the fit after the first is profiled on its own
(``torch.profiler``, CPU); a unit's GEMM seconds are the self time of the operators in :data:`GEMM_OPS`. The timed
units are grouped into repeats as the benchmark groups them, and the median repeat is taken. The profiler slows the
other operators, not the products, so the repeat's own seconds come from ``--rates``: the current and the baseline
side of a ``bench_learners.py --baseline REV`` run ON THIS MACHINE (the ratio means nothing across machines; the
JSON records this one's CPU). Both must hold the item with the settings hash this run measures.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

import bench_learners

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
ITEMS = tuple(bench_learners.GOALS)
"""The learners with a speed-up goal (``bench_learners.GOALS``)."""
COUNTS = {"train": "rounds", "gradient": "steps"}
"""The counts of ``bench_learners.counts`` that time each phase a headline rate (``bench_learners.HEADLINE``) is of."""
GEMM_OPS = frozenset({"aten::mm", "aten::addmm", "aten::bmm", "aten::baddbmm", "aten::_addmm_activation",
                      "aten::mkldnn_convolution", "aten::convolution_backward", "aten::mkldnn_linear",
                      "mkldnn::_linear_pointwise", "mkldnn::_convolution_pointwise"})
"""Operators whose self time is a matrix product or a convolution (forward or backward)."""
GOAL = 3.0


def gemm_seconds(averages) -> tuple[float, dict[str, float]]:
    """(GEMM self seconds, {operator: self seconds} of every operator) of a profiler's ``key_averages()``."""
    by_op: dict[str, float] = {}
    for event in averages:
        by_op[event.key] = by_op.get(event.key, 0.0) + event.self_cpu_time_total / 1e6
    return sum(s for op, s in by_op.items() if op in GEMM_OPS), by_op


def repeats(per_unit: list[float | None], *, head: int, repeats_: int, group: int) -> list[float]:
    """Sums of ``group`` consecutive units from unit ``head`` on, ``repeats_`` of them (as ``_learner_probes.grouped``
    groups the timed units)."""
    body = per_unit[head:head + repeats_ * group]
    if len(body) < repeats_ * group or any(v is None for v in body):
        raise RuntimeError(f"expected {repeats_ * group} profiled units from unit {head}, found "
                           f"{sum(v is not None for v in body)}")
    return [sum(body[i:i + group]) for i in range(0, len(body), group)]


def ceiling(*, baseline_s: float, current_s: float, gemm_s: float, goal: float = GOAL) -> dict:
    """The speed-up now, its ceiling at the current GEMM time and the non-GEMM seconds the goal leaves per repeat."""
    return {"speedup": round(baseline_s / current_s, 3), "ceiling": round(baseline_s / gemm_s, 3),
            "gemm_share": round(gemm_s / current_s, 3), "other_s_now": round(current_s - gemm_s, 4),
            "other_s_at_goal": round(baseline_s / goal - gemm_s, 4)}


# ---- the worker: one item, profiled unit by unit --------------------------------------------------------------
def profile_item(item: str, tensor_dir: Path, profile: str) -> dict:
    """The item's GEMM seconds per timed repeat, and the self seconds of the operators over every profiled unit
    (``top_ops_s``, ``gemm_ops_s``: the warm-up's and, for TD-MPC, its own episodes' units included)."""
    import _learner_probes as P
    from torch.profiler import ProfilerActivity
    from torch.profiler import profile as torch_profile

    per_unit: list[float | None] = []
    totals: dict[str, float] = {}
    state: dict = {"prof": None}
    original = P.Recorder.step

    def step(self, **kwargs):
        prof = state.pop("prof", None)
        if prof is None:
            per_unit.append(None)          # the first unit (the run's set-up) is not profiled
        else:
            prof.__exit__(None, None, None)
            seconds, by_op = gemm_seconds(prof.key_averages())
            per_unit.append(seconds)
            for op, s in by_op.items():
                totals[op] = totals.get(op, 0.0) + s
        out = original(self, **kwargs)     # raises Enough at the probe's last unit: nothing is profiled after it
        state["prof"] = torch_profile(activities=[ProfilerActivity.CPU])
        state["prof"].__enter__()
        return out

    P.Recorder.step = step
    try:
        result = bench_learners.measure_item(item, tree=ROOT, tensor_dir=tensor_dir, profile=profile, quick=False)
    finally:
        P.Recorder.step = original
        if state.get("prof") is not None:
            state["prof"].__exit__(None, None, None)
    phase = bench_learners.HEADLINE[item].split(".")[0]
    counts = bench_learners.counts(False)[COUNTS[phase]]
    head = result.get("ramp_units", 0) + counts.warmup
    gemm = repeats(per_unit, head=head, repeats_=counts.repeats, group=counts.group)
    top = sorted(totals.items(), key=lambda kv: -kv[1])
    return {"item": item, "settings_hash": result["settings_hash"], "phase": phase, "units_per_repeat": counts.group,
            "gemm_s_per_repeat": {"median_s": statistics.median(gemm), "min_s": min(gemm), "max_s": max(gemm),
                                  "repeats": len(gemm)},
            "top_ops_s": {op: round(s, 4) for op, s in top[:12]},
            "gemm_ops_s": {op: round(s, 4) for op, s in top if op in GEMM_OPS}}


# ---- the run ---------------------------------------------------------------------------------------------------
def cpu() -> dict:
    """This machine's CPU model and its bfloat16 product instructions (from /proc/cpuinfo where it exists)."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return {"model": None}
    model = next((line.split(":", 1)[1].strip() for line in text.splitlines() if line.startswith("model name")), None)
    flags = next((line.split(":", 1)[1].split() for line in text.splitlines() if line.startswith("flags")), [])
    return {"model": model, "avx512_bf16": "avx512_bf16" in flags, "amx_bf16": "amx_bf16" in flags}


def rates_for(item: str, files: list[Path]) -> tuple[dict, Path]:
    """The last ``--rates`` file's entry for ``item`` with both sides measured, with the file's baseline revision
    (``baseline_rev``)."""
    found = None
    for path in files:
        payload = json.loads(path.read_text())
        entry = payload.get("learners", {}).get(item)
        if entry and entry.get("baseline") and "error" not in entry["baseline"] and "error" not in entry["current"]:
            found = ({**entry, "baseline_rev": payload["trees"]["baseline"]["rev"]}, path)
    if found is None:
        raise SystemExit(f"gemm_ceiling: no side-by-side rates of {item} in {', '.join(map(str, files))}; expected "
                         f"the output of `python benchmarks/bench_learners.py --items {item} --baseline REV`")
    return found


def summarize(item: str, measured: dict, entry: dict, source: Path) -> dict:
    """One item's line of the result: the rates file's repeat seconds beside this run's GEMM seconds."""
    phase = measured["phase"]
    if entry["current"]["settings_hash"] != measured["settings_hash"]:
        raise SystemExit(f"gemm_ceiling: {source}: {item}'s current side has settings hash "
                         f"{entry['current']['settings_hash']}, this tree's is {measured['settings_hash']}; rerun "
                         "bench_learners.py on this tree")
    current_s = entry["current"][phase]["seconds_per_repeat"]["median_s"]
    baseline_s = entry["baseline"][phase]["seconds_per_repeat"]["median_s"]
    gemm_s = measured["gemm_s_per_repeat"]["median_s"]
    rel = source.resolve().relative_to(ROOT) if source.resolve().is_relative_to(ROOT) else source
    return {"rates_from": str(rel), "baseline_rev": entry["baseline_rev"], "phase": phase,
            "baseline_s_per_repeat": baseline_s,
            "current_s_per_repeat": current_s, **measured, **ceiling(baseline_s=baseline_s, current_s=current_s,
                                                                     gemm_s=gemm_s)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rates", type=Path, action="append", default=[],
                    help="a bench_learners.py --baseline JSON of this machine (repeatable; the last with an item wins)")
    ap.add_argument("--tensor", type=Path, default=Path("results/data/milan"), help="a prepared tensor directory")
    ap.add_argument("--profile", default="paper", help="the config profile whose sizes are measured")
    ap.add_argument("--items", nargs="+", default=list(ITEMS), choices=ITEMS)
    ap.add_argument("--out", type=Path, default=HERE / "results" / "gemm_ceiling_cpu_t1.json")
    ap.add_argument("--worker", choices=ITEMS, help=argparse.SUPPRESS)
    ap.add_argument("--worker-out", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args()
    args.tensor = args.tensor.resolve()
    if args.worker:
        args.worker_out.write_text(json.dumps(profile_item(args.worker, args.tensor, args.profile)) + "\n")
        return
    if not args.rates:
        raise SystemExit("gemm_ceiling: --rates is required: a bench_learners.py --baseline JSON of this machine")
    entries = {item: rates_for(item, args.rates) for item in args.items}   # fail before the long runs
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT / "src"), str(ROOT)]), "OMP_NUM_THREADS": "1",
           "MKL_NUM_THREADS": "1"}
    out: dict[str, dict] = {}
    with tempfile.TemporaryDirectory(prefix="gemm-ceiling-") as tmp:
        for item in args.items:
            target = Path(tmp) / f"{item}.json"
            proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--worker", item, "--worker-out",
                                   str(target), "--tensor", str(args.tensor), "--profile", args.profile], env=env,
                                  capture_output=True, text=True)
            if proc.returncode != 0:
                raise SystemExit(f"gemm_ceiling: {item} failed (exit {proc.returncode}):\n{proc.stderr[-4000:]}")
            entry, source = entries[item]
            row = summarize(item, json.loads(target.read_text()), entry, source)
            out[item] = row
            print(f"{item:18s} baseline {row['baseline_s_per_repeat']:8.3f} s  now {row['current_s_per_repeat']:8.3f} s"
                  f"  GEMM {row['gemm_s_per_repeat']['median_s']:8.3f} s ({row['gemm_share']:.0%})  speed-up "
                  f"{row['speedup']:.2f}x  ceiling {row['ceiling']:.2f}x  other at 3x {row['other_s_at_goal']:+.3f} s",
                  flush=True)
    from _timing import write_to

    path = write_to(args.out, {"profile": args.profile, "threads": 1, "cpu": cpu(), "goal_speedup": GOAL,
                               "gemm_ops": sorted(GEMM_OPS), "learners": out})
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
