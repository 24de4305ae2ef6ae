"""A learner's snapshots (or a reference method) scored on the learning curves' validation days (one MLflow run,
kind "learning"); results/learning/..., never a table's source."""
import sys
from pathlib import Path

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (injected by Snakemake)

from dswm.pipeline.learning import learning_score_job
from dswm.settings import read_param

w, inp, p = snakemake.wildcards, snakemake.input, snakemake.params  # noqa: F821
learning_score_job(job=read_param(p.settings), mlflow_cfg=p.tracking.value, display=p.display.value,
                   tensor_dir=Path(inp.tensor).parent, dataset=w.dataset, method=w.method, seed=int(w.seed),
                   out=snakemake.output.curve, repo=snakemake.scriptdir + "/../..",  # noqa: F821
                   snapshots_dir=inp.get("snapshots"),  # the learner's snapshots; None for a reference method
                   intensity=inp.get("intensity"))  # the calibrate rule's record, or None
