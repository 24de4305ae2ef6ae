"""The `tables` target: the tables in place still rest on a passing audit of the files as they are now.

Runs on every `snakemake tables` (a target without output). The gate of build_tables is applied again: the report
passed, audits this profile and these settings, and every file it vouches for hashes as the audit found it. When
it does not, the tables are removed (they were built from files that are no longer there as audited) and the
call fails with the reasons; the next `snakemake tables` rebuilds them once the tree passes an audit again.
"""
import sys
from pathlib import Path

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (injected by Snakemake)

from audits.runner import gate
from dswm.settings import read_param

inp = snakemake.input  # noqa: F821
refusals = gate(inp.report, expect=read_param(snakemake.params.audit), root=Path.cwd())  # noqa: F821
if refusals:
    removed = [t for t in inp.tables if Path(t).exists()]
    for t in removed:
        Path(t).unlink()
    lines = [f"tables refused: {line}" for line in refusals]
    if removed:
        lines.append(f"tables refused: removed {len(removed)} table file(s) built before the change: "
                     f"{', '.join(removed)}")
    for line in lines:
        print(line, file=sys.stderr)
        print(line, file=sys.__stderr__)
    sys.exit(1)
print(f"tables: {len(inp.tables)} files rest on {inp.report}, which passed and vouches for every file as it is "
      f"now: {', '.join(inp.tables)}", file=sys.stderr)
