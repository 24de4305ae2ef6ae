"""Build the paper's two tables from the per-day result files."""
import sys
from pathlib import Path

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (injected by Snakemake)

from dswm.jobs import tables_job

inp = snakemake.input  # noqa: F821
frames = tables_job(config=snakemake.config, result_paths=list(inp.results),  # noqa: F821
                    meta_paths={d: getattr(inp, d) for d in snakemake.params.datasets},  # noqa: F821
                    out_dir=Path(snakemake.output.main_md).parent)  # noqa: F821
for name, df in frames.items():
    print(f"{name}:\n{df}", file=sys.stderr)
