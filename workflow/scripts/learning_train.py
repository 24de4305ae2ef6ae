"""One learner's learning run: trained at its cap on the training days less the validation days, with the snapshots
of the untrained model and of the ladder (one MLflow run, kind "learning"); results/learning/..., never a table's
source."""
import sys
from pathlib import Path

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (injected by Snakemake)

from dswm.pipeline.learning import learning_train_job
from dswm.settings import read_param

w, out, p = snakemake.wildcards, snakemake.output, snakemake.params  # noqa: F821
learning_train_job(job=read_param(p.settings), mlflow_cfg=p.tracking.value,
                   tensor_dir=Path(snakemake.input.tensor).parent, dataset=w.dataset, method=w.method,  # noqa: F821
                   seed=int(w.seed), model_out=out.model, manifest_out=out.manifest, history_out=out.history,
                   snapshots_out=out.snapshots, run_dir=p.run_dir, repo=snakemake.scriptdir + "/../..",  # noqa: F821
                   intensity=snakemake.input.get("intensity"))  # noqa: F821 (the calibrate rule's record, or None)
