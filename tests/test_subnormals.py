"""Every job flushes subnormal floats to zero (dswm.pipeline.subnormals), on its own thread and on the worker
threads started after it. The check runs in a fresh interpreter: the mode is a property of the process's threads, and
tests that run a job in this process set it here too."""
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
    assert got["before"] == float(torch.tensor(2e-39))       # subnormal, computed, before the job's setup
    assert got["after"] == 0.0 and got["thread"] == 0.0
    assert got["parallel_nonzero"] == 0 and got["threads"] == 2

