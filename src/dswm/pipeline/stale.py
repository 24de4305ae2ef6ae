"""Tables that no longer rest on their sources are withdrawn, so they cannot be taken for current results.

The tables are built only from a passing audit report that vouches for every file they rest on (its SHA-256;
``audits.runner.gate``). When a file it vouches for goes (a rerun's job deletes its outputs before it runs, and a
failed job leaves none) or changes, the tables in place describe a tree that no longer exists: the `tables` target
(workflow/scripts/tables_check.py) and the workflow's `onerror` handler (workflow/rules/tables.smk) remove them; the
next successful `snakemake tables` builds them again.
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence


def withdraw_tables(tables: Sequence[str | Path], reasons: Sequence[str]) -> list[str]:
    """Remove the table files of ``tables`` that exist when ``reasons`` is not empty; returns the lines to print.

    Args:
        tables: the table files (the build_tables rule's outputs).
        reasons: why the tables no longer rest on their sources (``audits.runner.gate``'s messages); empty: they
            do, and nothing is removed.

    Returns:
        Each reason prefixed "tables withdrawn: ", then one line naming the files removed (none when no table
        existed, or when ``reasons`` is empty).
    """
    if not reasons:
        return []
    removed = [str(t) for t in tables if Path(t).exists()]
    for t in removed:
        Path(t).unlink()
    if not removed:
        return []
    return [f"tables withdrawn: {r}" for r in reasons] + [
        f"tables withdrawn: removed {len(removed)} table file(s) built from files that are no longer there as audited "
        f"(run `snakemake --cores 2 tables` to build them again): {', '.join(removed)}"]
