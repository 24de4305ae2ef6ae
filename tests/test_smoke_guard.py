"""The hang guards of the smoke runs that the integration and cluster tests share (tests/smoke.py,
tests/cluster/background.py): a run past its limit is stopped, and the failure names the run and how far it got."""
from __future__ import annotations

import json
import subprocess
import sys
import time

import pytest

import smoke
from cluster.background import SlurmSmokeRun


def fake_snakemake(script: str):
    """A ``command_of`` for smoke.run_smoke: a shell running ``script`` in place of Snakemake, the call's arguments
    in ``$*`` (passed to the call, not patched into the module: its run in the background, conftest.local_smoke, may
    start a call meanwhile)."""
    return lambda *args, **kwargs: (["bash", "-c", script, "snakemake", *args], None)


def test_progress_is_snakemakes_last_steps_line():
    text = "Select jobs to execute...\n1 of 77 steps (1%) done\nrule train:\n41 of 77 steps (53%) done\nrule evaluate:\n"
    assert smoke.progress(text) == "41 of 77 steps (53%) done"
    assert smoke.progress("Building DAG of jobs...\n") == "no job had finished"


def test_a_local_smoke_call_past_its_hang_guard_is_stopped_naming_the_call_and_how_far_it_got(tmp_path):
    fake = fake_snakemake("echo '5 of 77 steps (6%) done' >&2; echo $$ > pid; exec sleep 600")
    with pytest.raises(AssertionError) as err:
        smoke.run_smoke(tmp_path, "tables", "tables", "calibrate", limit_s=3, command_of=fake)
    assert str(err.value) == (
        f"the local smoke run `snakemake tables calibrate --cores 2` in {tmp_path} did not end within 3 s (its hang "
        f"guard, tests/smoke.py LIMIT_S): 5 of 77 steps (6%) done when it was stopped; its output: "
        f"{tmp_path / 'smoke_tables.out'}")
    pid = int((tmp_path / "pid").read_text())
    assert subprocess.run(["kill", "-0", str(pid)], capture_output=True).returncode != 0  # stopped
    assert not (tmp_path / smoke.TIMING).exists()


def test_a_failed_local_smoke_call_names_the_call_how_far_it_got_and_its_output(tmp_path):
    fake = fake_snakemake("echo '40 of 77 steps (52%) done'; echo 'Error in rule train' >&2; exit 1")
    with pytest.raises(AssertionError, match=r"^the local smoke run `snakemake figures --cores 2` in .* exited with 1 "
                                             r"after [\d.]+ s, 40 of 77 steps \(52%\) done; its output \(.*"
                                             r"smoke_figures\.out\):\n40 of 77 steps \(52%\) done\nError in rule train"):
        smoke.run_smoke(tmp_path, "figures", "figures", command_of=fake)


def test_each_smoke_call_adds_its_wall_time_to_the_timing_record(tmp_path):
    fake = fake_snakemake("echo '77 of 77 steps (100%) done'")
    smoke.run_smoke(tmp_path, "tables", "tables", "calibrate", command_of=fake)
    smoke.run_smoke(tmp_path, "figures", "figures", command_of=fake)
    timing = json.loads((tmp_path / smoke.TIMING).read_text())
    assert sorted(timing) == ["figures", "tables"] and all(isinstance(v, float) for v in timing.values())


def test_the_slurm_smoke_run_past_its_hang_guard_is_stopped_and_the_cluster_tests_are_told_how_far_it_got(tmp_path):
    log = tmp_path / "snakemake.out"
    log.write_text("Job 6 has been submitted with SLURM jobid 1\n12 of 35 steps (34%) done\n")
    run = SlurmSmokeRun(root=tmp_path, work=tmp_path / "repo", log=log, limit_s=2,
                        argv=[sys.executable, "tables", "calibrate", "--executor", "slurm"])
    run.proc = subprocess.Popen(["sleep", "600"], start_new_session=True)
    run.started = time.monotonic()
    run.settle()  # never raises: the local smoke run follows it whatever became of it
    assert run.proc.poll() is not None
    message = (f"the SLURM smoke run (`snakemake tables calibrate --executor slurm` in {tmp_path / 'repo'}) did not "
               f"end within 2 s (its hang guard, tests/cluster/background.py LIMIT_S): 12 of 35 steps (34%) done "
               f"when it was stopped; its output: {log}")
    assert run.overrun == message
    with pytest.raises(RuntimeError) as err:
        run.wait()
    assert str(err.value) == message


def test_the_background_run_hands_each_call_to_its_readers_and_a_failed_call_fails_the_later_ones(tmp_path):
    fake = fake_snakemake('case "$*" in *figures*) echo ran > figures_ran;; esac; echo "$*" >> calls; exit 3')
    run = smoke.LocalSmokeRun(tmp_path / "repo", ("tables", "figures"), command_of=fake).launch()
    with pytest.raises(AssertionError, match=r"`snakemake tables calibrate --cores 2` in .* exited with 3"):
        run.result("tables")
    with pytest.raises(AssertionError, match=r"`snakemake tables calibrate --cores 2` in .* exited with 3"):
        run.result("figures")  # figures reads the tables' outputs: it is not run, and says why
    assert (tmp_path / "repo" / "calls").read_text() == "tables calibrate --cores 2\n"
    assert not (tmp_path / "repo" / "figures_ran").exists()
    assert (tmp_path / "repo" / "Snakefile").exists()  # the run's own copy of the tree


def test_the_background_run_runs_its_calls_in_order_and_stop_ends_a_call_that_still_goes(tmp_path):
    fake = fake_snakemake('echo "$*" >> calls; case "$*" in *figures*) echo $$ > pid; exec sleep 600;; esac')
    run = smoke.LocalSmokeRun(tmp_path / "repo", ("tables", "figures"), command_of=fake).launch()
    assert run.result("tables") == tmp_path / "repo"
    deadline = time.monotonic() + 30
    while not (tmp_path / "repo" / "pid").exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    run.stop()
    with pytest.raises(AssertionError, match=r"`snakemake figures room_fill --cores 2` in .* exited with -15"):
        run.result("figures")
    pid = int((tmp_path / "repo" / "pid").read_text())
    assert subprocess.run(["kill", "-0", str(pid)], capture_output=True).returncode != 0  # stopped
    assert (tmp_path / "repo" / "calls").read_text() == "tables calibrate --cores 2\nfigures room_fill --cores 2\n"
