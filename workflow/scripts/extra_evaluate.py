"""Evaluate one (dataset, method, seed) under an extra run's variant on the figures' days (one MLflow run)."""
import sys
from pathlib import Path

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (injected by Snakemake)

from dswm.pipeline.extra import extra_evaluate_job
from dswm.pipeline.jobs import reused_inputs
from dswm.settings import read_param

w, inp, p, out = snakemake.wildcards, snakemake.input, snakemake.params, snakemake.output  # noqa: F821
extra_evaluate_job(job=read_param(p.settings), mlflow_cfg=p.tracking.value, variant=w.variant, display=p.display.value,
                   tensor_dir=Path(inp.tensor).parent, dataset=w.dataset, method=w.method, seed=int(w.seed),
                   days_out=out.days, trajectory_out=out.trajectory, record_out=out.record,
                   model=inp.get("model"), manifest=inp.get("manifest"),
                   repo=snakemake.scriptdir + "/../..",  # noqa: F821
                   intensity=inp.get("intensity"),  # the calibrate rule's record, or None
                   # the first seed's extra run, for a method the seed does not change (dswm.settings.reused_seed)
                   reuse=reused_inputs(inp))
