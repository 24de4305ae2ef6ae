"""Fit the room-fill candidate's rho_k and choose its gamma on training days (one MLflow run)."""
import sys
from pathlib import Path

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (injected by Snakemake)

from dswm.pipeline.room_fill import room_fill_fit_job
from dswm.settings import read_param

w, inp, p, out = snakemake.wildcards, snakemake.input, snakemake.params, snakemake.output  # noqa: F821
room_fill_fit_job(job=read_param(p.settings), mlflow_cfg=p.tracking.value, display=p.display.value,
                  tensor_dir=Path(inp.tensor).parent, dataset=w.dataset, variant=p.variant, seed=int(w.seed),
                  model=inp.model, manifest=inp.manifest, out=out.fit,
                  repo=snakemake.scriptdir + "/../..",  # noqa: F821
                  intensity=inp.get("intensity"))  # the calibrate rule's record, or None
