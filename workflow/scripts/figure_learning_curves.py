"""The learning curves (results/figures/learning_curves.{png,pdf,csv}) and each learner's verdict
(learning_verdict.csv), from the learning runs' score files and loss histories only."""
import sys

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (injected by Snakemake)

import json

from dswm.figures.common import read_parquets
from dswm.figures.learning import curve_table, draw_learning_curves, learning_verdict
from prep.atomic import atomic_path
from dswm.pipeline.history import read_histories

inp, p = snakemake.input, snakemake.params  # noqa: F821
out = {k: getattr(snakemake.output, k) for k in ("png", "pdf", "csv")}  # noqa: F821
with open(inp.meta, encoding="utf-8") as fh:
    source = json.load(fh)["source"]
table = curve_table(read_parquets(inp.curves), read_parquets(inp.references))
histories = read_histories(inp.histories)
verdict = learning_verdict(table, histories)
print(verdict.select("method", "return_rises", "sr_gain", "sr_learned", "learned", "learned_at_transitions",
                     "learned_at_gradient_steps"), file=sys.stderr)
draw_learning_curves(table, histories, order=p.methods, labels=p.labels, ladder=p.ladder, profile=p.profile,
                     source=source, out=out, verdict=verdict)
with atomic_path(snakemake.output.verdict) as tmp:  # noqa: F821
    verdict.write_csv(tmp)

from dswm.pipeline.tracking import attach_figure_outputs  # noqa: E402

attach_figure_outputs(p.attach.value, out)  # the figure beside the MLflow runs it shows
