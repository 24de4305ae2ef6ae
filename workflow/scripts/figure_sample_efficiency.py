"""Paper Fig. 9: the sample-efficiency probe's served ratio against environment transitions
(results/figures/sample_efficiency.{png,pdf,csv}), from the probe files only."""
import sys

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (injected by Snakemake)

import json

from dswm.figures.common import read_parquets
from dswm.figures.sample_efficiency import draw_sample_efficiency

inp, p = snakemake.input, snakemake.params  # noqa: F821
out = {k: getattr(snakemake.output, k) for k in ("png", "pdf", "csv")}  # noqa: F821
with open(inp.meta, encoding="utf-8") as fh:
    source = json.load(fh)["source"]
draw_sample_efficiency(read_parquets(inp.probes), order=p.methods, labels=p.labels, fractions=p.fractions,
                       profile=p.profile, source=source, out=out)

from dswm.pipeline.tracking import attach_figure_outputs  # noqa: E402

attach_figure_outputs(p.attach.value, out)  # the figure beside the MLflow runs it shows
