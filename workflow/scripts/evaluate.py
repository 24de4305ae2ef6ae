"""Evaluate one (dataset, method, seed) on the fixed ID and OOD days (one MLflow run)."""
import sys
from pathlib import Path

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (injected by Snakemake)

from dswm.pipeline.jobs import evaluate_job, reused_inputs
from dswm.settings import read_param

w, inp, p = snakemake.wildcards, snakemake.input, snakemake.params  # noqa: F821
evaluate_job(job=read_param(p.settings), mlflow_cfg=p.tracking.value, display=p.display.value,
             tensor_dir=Path(inp.tensor).parent, dataset=w.dataset, method=w.method, seed=int(w.seed),
             days_out=snakemake.output.days,  # noqa: F821
             trajectory_out=snakemake.output.trajectory, record_out=snakemake.output.record,  # noqa: F821
             model=inp.get("model"),
             manifest=inp.get("manifest"), repo=snakemake.scriptdir + "/../..",  # noqa: F821
             intensity=inp.get("intensity"),  # the calibrate rule's record, or None
             # the first seed's evaluation, for a method the seed does not change (dswm.settings.reused_seed)
             reuse=reused_inputs(inp))
