"""Train one learning method on one dataset's TRAINING days (one MLflow run)."""
import sys
from pathlib import Path

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (injected by Snakemake)

from dswm.pipeline.jobs import train_job
from dswm.settings import read_param

w, p = snakemake.wildcards, snakemake.params  # noqa: F821
train_job(job=read_param(p.settings), mlflow_cfg=p.tracking.value, evaluated_as=p.evaluated_as.value,
          tensor_dir=Path(snakemake.input.tensor).parent, dataset=w.dataset, method=w.method,  # noqa: F821
          seed=int(w.seed), model_out=snakemake.output.model, manifest_out=snakemake.output.manifest,  # noqa: F821
          run_dir=p.run_dir, repo=snakemake.scriptdir + "/../..",  # noqa: F821
          history_out=snakemake.output.history,  # noqa: F821 (the loss history, for the figures)
          snapshots_out=snakemake.output.snapshots,  # noqa: F821 (the probe's snapshots, or left empty)
          intensity=snakemake.input.get("intensity"))  # noqa: F821 (the calibrate rule's record, or None)
