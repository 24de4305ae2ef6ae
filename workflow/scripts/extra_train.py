"""Train one learning method under an extra run's variant (fleet size or demand intensity; one MLflow run)."""
import sys
from pathlib import Path

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (injected by Snakemake)

from dswm.pipeline.extra import extra_train_job
from dswm.settings import read_param

w, inp, p, out = snakemake.wildcards, snakemake.input, snakemake.params, snakemake.output  # noqa: F821
extra_train_job(job=read_param(p.settings), mlflow_cfg=p.tracking.value, variant=w.variant,
                tensor_dir=Path(inp.tensor).parent, dataset=w.dataset, method=w.method, seed=int(w.seed),
                model_out=out.model, manifest_out=out.manifest, run_dir=p.run_dir,
                repo=snakemake.scriptdir + "/../..",  # noqa: F821
                intensity=inp.get("intensity"))  # the calibrate rule's record, or None
