"""Figure foresight: demand source x planner, and the world model's RMSE (results/figures/foresight.{png,pdf,csv})."""
import sys

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (injected by Snakemake)

import polars as pl

from dswm.figures.common import read_days, read_parquets
from dswm.figures.foresight import draw_foresight, foresight_table
from dswm.protocol.tables import DATASET_LABELS
from dswm.settings import EvalDayLimits

inp, p = snakemake.input, snakemake.params  # noqa: F821
out = {k: getattr(snakemake.output, k) for k in ("png", "pdf", "csv")}  # noqa: F821
main = read_days(inp.main)
table = foresight_table(main, read_days(inp.runs) if inp.runs else None, p.cells, seeds=p.seeds,
                        limits=EvalDayLimits(**p.eval_days))
rmse = read_parquets(inp.rmse)
by_dataset = {d: rmse.filter(pl.col("dataset") == d) for d in p.cells} if rmse.height else {}
draw_foresight(table, by_dataset, dataset_labels=DATASET_LABELS, profile=p.profile,
               source=",".join(sorted(set(main["data_source"]))), out=out)

from dswm.pipeline.tracking import attach_figure_outputs  # noqa: E402

attach_figure_outputs(p.attach.value, out)  # the figure beside the MLflow runs it shows
