"""A place the workflow writes that cannot take a file is named before any job runs (not after ~40 s of jobs as a
raw traceback): a file where a rule writes a directory at parse time, an unwritable directory of the jobs about to
run as the workflow starts (workflow/rules/common.smk check_output_paths, check_outputs_writable).

The tests run as root, for whom a chmod stops no write: they put a FILE where a directory is written, which stops
every user, and check the permission branch of prep.atomic.write_obstacles with os.access answering as it does for
a user without write permission."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

from prep import atomic
from smoke import copy_tree, snakemake


@pytest.fixture
def tree(tmp_path):
    """A copy of the working tree, nothing run in it, with a results/ directory."""
    work = copy_tree(tmp_path / "repo")
    (work / "results").mkdir()
    return work


def nothing_ran(work: Path, obstacle: str) -> bool:
    """No job wrote anything: results/ holds the obstacle alone and no log directory exists."""
    return [p.name for p in (work / "results").iterdir()] == [obstacle] and not (work / "logs").exists()


def test_a_file_named_results_tables_is_named_before_any_job(tree):
    (tree / "results" / "tables").write_text("not a directory\n")
    proc = snakemake(tree, "tables", "--cores", "1", timeout=300)
    assert proc.returncode != 0
    assert ("results/tables is a file, not a directory: the outputs of build_tables cannot be written in "
            "results/tables; nothing was run (move the file away and run again)") in proc.stdout + proc.stderr
    assert "Traceback" not in proc.stdout + proc.stderr
    assert nothing_ran(tree, "tables")


def test_a_file_in_the_way_of_the_jobs_about_to_run_is_named_before_any_job(tree):
    (tree / "results" / "milan").write_text("not a directory\n")  # under a wildcard: known once the DAG is
    proc = snakemake(tree, "tables", "--cores", "1", timeout=300)
    assert proc.returncode != 0
    assert ("results/milan is a file, not a directory: the outputs of evaluate, train cannot be written in "
            "results/milan/ceiling/seed0, results/milan/dswm/seed0, results/milan/dswm_plus/seed0 and 16 "
            "more; nothing was run (move the file away and run again)") in proc.stdout + proc.stderr
    assert nothing_ran(tree, "milan")


def test_write_obstacles_judges_a_missing_directory_by_its_nearest_existing_ancestor(tmp_path, monkeypatch):
    (tmp_path / "file").write_text("x")
    (tmp_path / "ok").mkdir()
    (tmp_path / "locked").mkdir()
    paths = [tmp_path / "ok" / "new" / "deeper" / "a.csv", tmp_path / "file" / "tables" / "a.md",
             tmp_path / "file" / "b.md", tmp_path / "locked" / "sub" / "c.md"]
    assert atomic.write_obstacles(paths) == {
        tmp_path / "file": ("a file, not a directory", [tmp_path / "file", tmp_path / "file" / "tables"])}
    # as a user without write permission on `locked` (root, who runs the tests, writes through any chmod)
    real = os.access
    monkeypatch.setattr(atomic.os, "access", lambda p, mode: Path(p) != tmp_path / "locked" and real(p, mode))
    assert atomic.write_obstacles(paths)[tmp_path / "locked"] == ("a directory this user may not write to",
                                                                 [tmp_path / "locked" / "sub"])
