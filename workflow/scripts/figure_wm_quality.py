"""Paper Fig. 12: world-model quality on the test period (results/figures/wm_quality.{png,pdf,csv})."""
import sys

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (injected by Snakemake)

import polars as pl

from dswm.figures.wm_quality import draw_wm_quality
from dswm.protocol.tables import DATASET_LABELS
from prep.tensor import read_meta

inp, p = snakemake.input, snakemake.params  # noqa: F821
out = {k: getattr(snakemake.output, k) for k in ("png", "pdf", "csv")}  # noqa: F821
meta = read_meta(inp.meta, keys=("dataset", "source"))
draw_wm_quality(pl.concat([pl.read_parquet(f) for f in inp.rmse]), pl.concat([pl.read_parquet(f) for f in inp.returns]),
                dataset_label=DATASET_LABELS.get(meta["dataset"], meta["dataset"]), profile=p.profile,
                source=meta["source"], out=out)

from dswm.pipeline.tracking import attach_figure_outputs  # noqa: E402

attach_figure_outputs(p.attach.value, out)  # the figure beside the MLflow runs it shows
