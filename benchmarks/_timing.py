"""Small timing helpers shared by the benchmark scripts."""
from __future__ import annotations

import json
import os
import platform
import statistics
import time
from pathlib import Path
from typing import Callable, Sequence

RESULTS = Path(__file__).resolve().parent / "results"


def timed(run: Callable[[], object], *, setup: Callable[[], object] | None = None, repeats: int = 5,
          warmup: int = 1) -> dict:
    """Wall seconds of ``run()`` after ``warmup`` untimed calls: median, min and max of ``repeats`` timed calls
    (``setup()`` before each call, untimed)."""
    if repeats < 5:
        raise ValueError(f"repeats: expected at least 5, found {repeats}")
    times = []
    for i in range(warmup + repeats):
        if setup is not None:
            setup()
        t0 = time.perf_counter()
        run()
        if i >= warmup:
            times.append(time.perf_counter() - t0)
    return {"median_s": statistics.median(times), "min_s": min(times), "max_s": max(times), "repeats": repeats,
            "warmup": warmup}


def rate(timing: dict, work: float) -> dict:
    """``work`` per second at the median, and at the slowest and fastest repeat."""
    return {"median": work / timing["median_s"], "min": work / timing["max_s"], "max": work / timing["min_s"]}


def spread_ms(fn, *, reps: int = 30, warmup: int = 3) -> dict:
    """Median, min and max wall time of ``fn()`` in milliseconds over ``reps`` (>= 5) calls after ``warmup``."""
    timing = timed(fn, repeats=reps, warmup=warmup)
    return {"median_ms": round(1e3 * timing["median_s"], 3), "min_ms": round(1e3 * timing["min_s"], 3),
            "max_ms": round(1e3 * timing["max_s"], 3), "repeats": reps, "warmup": warmup}


def machine() -> dict:
    """What the figures were measured on, including the load at the time and whether the CPU has native bfloat16
    products (None: unknown; without them a ``matmul_dtype: bfloat16`` learner runs SLOWER than in float32)."""
    import torch

    from dswm.methods.matmul import native_bfloat16

    return {"platform": platform.platform(), "python": platform.python_version(), "torch": torch.__version__,
            "cpus": os.cpu_count(), "torch_threads": torch.get_num_threads(),
            "native_bfloat16": native_bfloat16(), "load_avg_1min": os.getloadavg()[0]}


def write(name: str, payload: dict) -> Path:
    """Write ``benchmarks/results/<name>.json`` atomically and print it."""
    path = write_to(RESULTS / f"{name}.json", payload)
    print(json.dumps(payload, indent=2))
    return path


def write_to(path: Path, payload: dict) -> Path:
    """Write ``payload`` with :func:`machine` to the JSON file ``path`` atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps({**payload, "machine": machine()}, indent=2) + "\n")
    os.replace(tmp, path)
    return path


def spread(times: Sequence[float], *, warmup: int) -> dict:
    """The summary :func:`timed` gives, of repeat times measured elsewhere (e.g. the units of a training loop)."""
    if len(times) < 5:
        raise ValueError(f"repeats: expected at least 5, found {len(times)}")
    return {"median_s": statistics.median(times), "min_s": min(times), "max_s": max(times), "repeats": len(times),
            "warmup": warmup}
