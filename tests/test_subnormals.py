"""Every job flushes subnormal floats to zero (dswm.pipeline.subnormals), on its own thread and on the worker
threads started after it. The check runs in a fresh interpreter: the mode is a property of the process's threads,
which the tests keep at the CPU's default (conftest.subnormals_kept)."""
import json
import subprocess
import sys

import torch

CHECK = r"""
import json, threading, torch
from types import SimpleNamespace
from dswm.pipeline.setup import init_process
tiny = lambda: float((torch.tensor([1e-39]) * 2.0).item())
before = tiny()
init_process(SimpleNamespace(torch_threads=2))
parallel = torch.full((2_000_000,), 1e-39) * 2.0      # split over torch's 2 worker threads, started after the mode
seen = {}
worker = threading.Thread(target=lambda: seen.setdefault("thread", tiny()))
worker.start(); worker.join()
print(json.dumps({"before": before, "after": tiny(), "parallel_nonzero": int((parallel != 0).sum()),
                  "thread": seen["thread"], "threads": torch.get_num_threads()}))
"""


def test_a_job_process_computes_a_subnormal_product_as_zero_on_every_thread_and_only_after_its_setup():
    out = subprocess.run([sys.executable, "-c", CHECK], capture_output=True, text=True, check=True)
    got = json.loads(out.stdout.strip().splitlines()[-1])
    # before the job's setup: 2e-39 in float32, a subnormal (below 2^-126 = 1.18e-38), computed
    assert 0.0 < got["before"] < 2.0 ** -126 and abs(got["before"] - 2e-39) < 1e-44
    assert got["after"] == 0.0 and got["thread"] == 0.0
    assert got["parallel_nonzero"] == 0 and got["threads"] == 2


def test_a_job_run_in_this_process_turns_it_on_and_every_call_does_so_again():
    from dswm.pipeline.subnormals import flush_subnormals

    tiny = lambda: float((torch.tensor([1e-39]) * 2.0).item())  # noqa: E731
    assert tiny() > 0.0                        # the tests' default mode (conftest.subnormals_kept)
    assert flush_subnormals() is True and tiny() == 0.0
    torch.set_flush_denormal(False)
    assert flush_subnormals() is True and tiny() == 0.0    # no cache: a second job in one process flushes too
