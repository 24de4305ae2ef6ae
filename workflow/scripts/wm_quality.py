"""World-model quality of one DSWM model (dataset, seed) on the main evaluation's days (one MLflow run, stage wm)."""
import sys
from pathlib import Path

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (injected by Snakemake)

from dswm.pipeline.wm import wm_quality_job
from dswm.settings import read_param

w, inp, out, p = snakemake.wildcards, snakemake.input, snakemake.output, snakemake.params  # noqa: F821
wm_quality_job(job=read_param(p.settings), mlflow_cfg=p.tracking.value, display=p.display.value,
               tensor_dir=Path(inp.tensor).parent, dataset=w.dataset, seed=int(w.seed), model=inp.model,
               manifest=inp.manifest, main_days=inp.main_days,
               rmse_out=out.rmse, returns_out=out.returns, maps_out=out.maps, record_out=out.record,
               repo=snakemake.scriptdir + "/../..",  # noqa: F821
               intensity=inp.get("intensity"))  # the calibrate rule's record, or None
