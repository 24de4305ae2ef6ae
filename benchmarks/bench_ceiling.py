"""The ceiling's convergence check: does doubling its search raise the per-slot ceiling by less than 0.001?

Run: python benchmarks/bench_ceiling.py [--results results] [--datasets milan shanghai yjmob] [--days 2]
[--double SETTING...]
Writes benchmarks/results/ceiling_doubling.json (``--name``). The datasets can run as separate processes, each with
its own ``--name``, and ``--merge NAME...`` then writes their reports, of the same settings, as one.
The committed ceiling_doubling.json was run on the DEMO tensors (``--results`` a demo run's results directory: its
``data/<dataset>`` and ``calibration/demand_intensity.json``; read only), 2 training days of each dataset, one
process per dataset merged with ``--merge``. Each dataset's entry records its tensor's source and SHA-256.

For each dataset, the ceiling (``dswm.methods.ceiling``) runs at the settings config.yaml ``ceiling`` gives and at
those settings doubled (``CeilingSettings.doubled``: twice the sweeps, refinement rounds and starts, twice the
lattice points per axis, twice the logit resolution) on ``--days`` TRAINING days of the prepared tensor
(``<results>/data/<dataset>``; evenly spread over the training segment, never a test day), through the evaluation
itself (``dswm.protocol.evaluation.evaluate``). Reported per dataset: each day's served ratio at both strengths,
the rise of each day, of the largest and of their mean, and the CPU milliseconds per day-slot of each evaluation (one
thread: the work done, whatever else the machine runs). The check passes when the mean served ratio of the days
rises by less than 0.001 on every dataset. ``--double SETTING...`` doubles only the settings named (``chains``,
``bw_logits``, ...), to find which one carries a rise; its report is not the check.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import time
from pathlib import Path

import numpy as np
import torch
import yaml

from _decisions import scenario_for
from _timing import RESULTS, write
from dswm import settings as runconfig
from dswm.config import to_plain, with_budget
from dswm.methods.ceiling import CeilingController, CeilingSettings
from dswm.protocol.evaluation import evaluate

ROOT = Path(__file__).resolve().parents[1]
TOLERANCE = 0.001
"""Largest rise of the checked days' mean served ratio that doubling may bring (config.yaml ``ceiling``)."""


def training_days(tensor, n: int) -> list[int]:
    """``n`` tensor days evenly spread over the TRAINING segment (first and last included)."""
    train = [int(d) for d in tensor.train_days]
    picks = np.unique(np.linspace(0, len(train) - 1, min(n, len(train))).round().astype(int))
    return [train[i] for i in picks]


def run(tensor, scenario, settings: CeilingSettings, days: list[int]) -> tuple[dict[str, float], float]:
    """({day label: served ratio}, CPU ms per day-slot of the whole evaluation) of the ceiling at ``settings`` on
    ``days``. CPU time, not wall time: on one thread it is the work done, whatever else the machine runs."""
    ctl = CeilingController(name="ceiling", options=settings)
    t0 = time.process_time()
    out = evaluate(tensor=tensor, controller=ctl, scenario=scenario, seed=0, limits={"id": None, "ood": None},
                   profile="bench", device="cpu", batch_days=True, progress_interval_s=60.0, trajectory=False,
                   days={"train": days})
    cpu_ms = 1e3 * (time.process_time() - t0) / (len(days) * (scenario.slots_per_day - 1))
    return {r["label"]: r["sr_mean"] for r in out.days.iter_rows(named=True)}, cpu_ms


def sha256(tensor_dir: Path) -> str:
    """SHA-256 of a prepared tensor's demand.parquet: which tensor the numbers were measured on."""
    return hashlib.sha256((tensor_dir / "demand.parquet").read_bytes()).hexdigest()


def merge(names: list[str], name: str) -> None:
    """Write the reports ``names`` (one or more datasets each, the same settings, tolerance and intensity) as one."""
    parts = [json.loads((RESULTS / f"{n}.json").read_text()) for n in names]
    keys = ("settings", "doubled", "tolerance", "intensity_from")
    for n, part in zip(names, parts):
        for key in keys:
            if part[key] != parts[0][key]:
                raise ValueError(f"benchmarks/results/{n}.json: {key} is {part[key]!r}; expected {parts[0][key]!r} "
                                 f"as in benchmarks/results/{names[0]}.json (only reports of one search merge)")
    report = {**{key: parts[0][key] for key in keys}, "datasets": {}, "merged_from": {}}
    for n, part in zip(names, parts):
        report["datasets"].update(part["datasets"])
        report["merged_from"][n] = part["machine"]
    report["passes"] = all(r["passes"] for r in report["datasets"].values())
    write(name, report)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--results", default="results", help="the results directory holding data/<dataset>")
    ap.add_argument("--datasets", nargs="+", default=["milan", "shanghai", "yjmob"])
    ap.add_argument("--days", type=int, default=2, help="training days per dataset")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--double", nargs="+", metavar="SETTING", help="double only these settings (e.g. chains fresh: "
                    "which one carries the rise); every setting when left out, as the check")
    ap.add_argument("--name", default="ceiling_doubling", help="benchmarks/results/<name>.json")
    ap.add_argument("--merge", nargs="+", metavar="NAME", help="write the reports benchmarks/results/<NAME>.json "
                    "(of the same settings) as one, benchmarks/results/<name>.json, and run nothing")
    args = ap.parse_args()
    if args.merge:
        merge(args.merge, args.name)
        return
    torch.set_num_threads(args.threads)
    from prep.tensor import load

    config = yaml.safe_load((ROOT / "config.yaml").read_text())
    settings = runconfig.resolve(config)
    results = ROOT / args.results
    scenario, source = scenario_for(settings, results / "calibration" / "demand_intensity.json", ROOT)
    base = runconfig.build(CeilingSettings, *with_budget(config["ceiling"], "demo", "ceiling"))  # the demo's = the paper's
    doubled = base.doubled(args.double)
    report = {"settings": to_plain(base), "doubled": to_plain(doubled), "tolerance": TOLERANCE,
              "intensity_from": source, "datasets": {}}
    for ds in args.datasets:
        tensor = load(results / "data" / ds)
        days = training_days(tensor, args.days)
        assert set(days) <= {int(d) for d in tensor.train_days}  # never a test day
        print(f"{ds}: training days {[tensor.labels[d] for d in days]}", flush=True)
        sr_base, ms_base = run(tensor, scenario, base, days)
        print(f"{ds}: served ratio {sr_base} at {ms_base:.1f} CPU ms per day-slot; now doubled", flush=True)
        sr_double, ms_double = run(tensor, scenario, doubled, days)
        rise = {d: sr_double[d] - sr_base[d] for d in sr_base}
        report["datasets"][ds] = {
            "tensor": {"source": str(tensor.meta["source"]), "demand_sha256": sha256(results / "data" / ds)},
            "days": list(sr_base), "served_ratio": sr_base, "served_ratio_doubled": sr_double,
            "rise": rise, "largest_rise": max(rise.values()),
            "mean": float(np.mean(list(sr_base.values()))), "mean_doubled": float(np.mean(list(sr_double.values()))),
            "cpu_ms_per_day_slot": round(ms_base, 1), "cpu_ms_per_day_slot_doubled": round(ms_double, 1),
            "mean_rise": float(np.mean(list(rise.values()))),
            "passes": float(np.mean(list(rise.values()))) < TOLERANCE}
        print(ds, report["datasets"][ds], flush=True)
    report["passes"] = all(r["passes"] for r in report["datasets"].values())
    write(args.name, report)


if __name__ == "__main__":
    main()
