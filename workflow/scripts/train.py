"""Train one learning method on one dataset's TRAINING days (one MLflow run)."""
import sys
from pathlib import Path

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (injected by Snakemake)

from dswm.jobs import train_job

w = snakemake.wildcards  # noqa: F821
train_job(config=snakemake.config, tensor_dir=Path(snakemake.input.tensor).parent,  # noqa: F821
          dataset=w.dataset, method=w.method, seed=int(w.seed), model_out=snakemake.output.model,  # noqa: F821
          manifest_out=snakemake.output.manifest, run_dir=snakemake.params.run_dir,  # noqa: F821
          repo=snakemake.scriptdir + "/../..")  # noqa: F821
