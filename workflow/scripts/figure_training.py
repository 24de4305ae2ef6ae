"""Paper Fig. 11: DSWM's training diagnostics per dataset (results/figures/training.{png,pdf,csv})."""
import sys

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (injected by Snakemake)

from dswm.figures.training import draw_training
from dswm.pipeline.history import read_histories
from dswm.protocol.tables import DATASET_LABELS
from prep.tensor import read_meta

inp, p = snakemake.input, snakemake.params  # noqa: F821
out = {k: getattr(snakemake.output, k) for k in ("png", "pdf", "csv")}  # noqa: F821
sources = {DATASET_LABELS.get(m["dataset"], m["dataset"]): m["source"]
           for m in (read_meta(path, keys=("dataset", "source")) for path in inp.metas)}
draw_training(read_histories(inp.histories), datasets=p.datasets, labels=DATASET_LABELS, profile=p.profile,
              source=sources, out=out)

from dswm.pipeline.tracking import attach_figure_outputs  # noqa: E402

attach_figure_outputs(p.attach.value, out)  # the figure beside the MLflow runs it shows
