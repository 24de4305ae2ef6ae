"""Build the paper's two tables from the per-day result files."""
import sys
from pathlib import Path

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (injected by Snakemake)

from dswm.pipeline.jobs import tables_job
from dswm.settings import read_param

inp = snakemake.input  # noqa: F821
job = read_param(snakemake.params.settings)  # noqa: F821
frames = tables_job(job=job, result_paths=list(inp.results), meta_paths={d: getattr(inp, d) for d in job["datasets"]},
                    out_dir=Path(snakemake.output.main_md).parent)  # noqa: F821
for name, df in frames.items():
    print(f"{name}:\n{df}", file=sys.stderr)
