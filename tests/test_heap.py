import json
import subprocess
import sys

from conftest import ROOT

# Run in a process of its own: a frozen heap stays frozen, and this one is pytest's. The callback registered FIRST runs
# LAST at exit (atexit is last in, first out), so it sees what the job's own freeze at exit did.
JOB = """
import atexit, gc, json, sys
seen = {}
atexit.register(lambda: sys.stdout.write(json.dumps({**seen, "at_exit": gc.get_freeze_count()})))
from dswm.pipeline.setup import prepare_process
seen["before"] = gc.get_freeze_count()
prepare_process(1)
seen["after_setup"] = gc.get_freeze_count()
made_later = [[i] for i in range(100_000)]         # a job's own objects: collected as usual until the exit
seen["later"] = gc.get_freeze_count()
"""


def test_a_jobs_process_freezes_its_imported_heap_at_setup_and_everything_at_exit():
    out = subprocess.run([sys.executable, "-c", JOB], capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    seen = json.loads(out.stdout)
    assert seen["before"] == 0
    assert seen["after_setup"] > 100_000              # torch, MLflow and the rest, imported by the job's setup
    assert seen["later"] == seen["after_setup"]       # objects made after the setup are not frozen by it
    assert seen["at_exit"] > seen["later"] + 90_000   # ... but are at exit (less what was freed meanwhile)
