"""The learning curves (results/figures/learning_curves.{png,pdf,csv}), from the learning runs' score files and
loss histories only."""
import sys

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (injected by Snakemake)

import json

from dswm.figures.common import read_parquets
from dswm.figures.learning import curve_table, draw_learning_curves
from dswm.pipeline.history import read_histories

inp, p = snakemake.input, snakemake.params  # noqa: F821
out = {k: getattr(snakemake.output, k) for k in ("png", "pdf", "csv")}  # noqa: F821
with open(inp.meta, encoding="utf-8") as fh:
    source = json.load(fh)["source"]
table = curve_table(read_parquets(inp.curves), read_parquets(inp.references))
draw_learning_curves(table, read_histories(inp.histories), order=p.methods, labels=p.labels, ladder=p.ladder,
                     profile=p.profile, source=source, out=out)

from dswm.pipeline.tracking import attach_figure_outputs  # noqa: E402

attach_figure_outputs(p.attach.value, out)  # the figure beside the MLflow runs it shows
