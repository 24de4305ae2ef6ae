"""Evaluate one arm of figure room_fill on the test days of its regime (one MLflow run)."""
import sys
from pathlib import Path

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (injected by Snakemake)

from dswm.pipeline.room_fill import room_fill_evaluate_job
from dswm.settings import read_param

w, inp, p, out = snakemake.wildcards, snakemake.input, snakemake.params, snakemake.output  # noqa: F821
fit = inp.get("fit") or None  # the candidate's fit record; an empty list for the other arms
fit = fit[0] if isinstance(fit, list) else fit
room_fill_evaluate_job(job=read_param(p.settings), fit=fit, mlflow_cfg=p.tracking.value,
                       variant=p.variant, display=p.display.value, tensor_dir=Path(inp.tensor).parent,
                       dataset=w.dataset, method=p.method, seed=int(w.seed), days_out=out.days,
                       trajectory_out=out.trajectory, record_out=out.record, model=inp.get("model"),
                       manifest=inp.get("manifest"), repo=snakemake.scriptdir + "/../..",  # noqa: F821
                       intensity=inp.get("intensity"))  # the calibrate rule's record, or None
