"""Build the paper's two tables from the per-day result files, once the leakage audit's report lets them be built."""
import sys
from pathlib import Path

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (injected by Snakemake)

from audits.runner import gate
from dswm.pipeline.jobs import tables_job
from dswm.settings import read_param

inp = snakemake.input  # noqa: F821
# Before any table is written: the report passed, audits this profile and these settings, and every file it vouches
# for still hashes as the audit found it. Otherwise nothing is written.
refusals = gate(inp.audit, expect=read_param(snakemake.params.audit), root=Path.cwd())  # noqa: F821
if refusals:
    for line in refusals:
        print(f"tables refused: {line}", file=sys.stderr)
        print(f"tables refused: {line}", file=sys.__stderr__)
    sys.exit(1)
job = read_param(snakemake.params.settings)  # noqa: F821
frames = tables_job(job=job, result_paths=list(inp.results), meta_paths={d: getattr(inp, d) for d in job["datasets"]},
                    out_dir=Path(snakemake.output.main_md).parent, database=snakemake.output.db)  # noqa: F821
for name, df in frames.items():
    print(f"{name}:\n{df}", file=sys.stderr)
