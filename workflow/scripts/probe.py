"""The sample-efficiency probe of one (dataset, method, seed): every model snapshot of its train job on the probe's
fixed test day (one MLflow run, stage "probe"); results/probes/..., never a table's source."""
import sys
from pathlib import Path

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (injected by Snakemake)

from dswm.pipeline.probe import probe_job
from dswm.settings import read_param

w, inp, p = snakemake.wildcards, snakemake.input, snakemake.params  # noqa: F821
probe_job(job=read_param(p.settings), mlflow_cfg=p.tracking.value, display=p.display.value,
          tensor_dir=Path(inp.tensor).parent, dataset=w.dataset, method=w.method, seed=int(w.seed),
          snapshots_dir=inp.snapshots,
          evaluation=inp.evaluation,  # the job's own evaluation: its value on the probe day is recorded
          out=snakemake.output.probe, record_out=snakemake.output.record,  # noqa: F821
          repo=snakemake.scriptdir + "/../..",  # noqa: F821
          intensity=inp.get("intensity"))  # the calibrate rule's record, or None
