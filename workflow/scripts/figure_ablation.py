"""Paper Fig. 8: DSWM against its ablations and the do(s) probe (results/figures/ablation.{png,pdf,csv})."""
import sys

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (injected by Snakemake)

from dswm.figures.ablation import do_probe_days, draw_ablation
from dswm.figures.common import read_days
from dswm.settings import EvalDayLimits

inp, p = snakemake.input, snakemake.params  # noqa: F821
out = {k: getattr(snakemake.output, k) for k in ("png", "pdf", "csv")}  # noqa: F821
ablation = read_days(inp.ablation)
probe = do_probe_days(read_days(inp.reference), read_days(inp.probe) if inp.probe else None,
                      methods=p.probe_methods, seeds=p.seeds, limits=EvalDayLimits(**p.eval_days))
draw_ablation(ablation, probe, order=p.order, labels=p.labels, split_labels=p.split_labels, profile=p.profile,
              source=",".join(sorted(set(ablation["data_source"]))), out=out)

from dswm.pipeline.tracking import attach_figure_outputs  # noqa: E402

attach_figure_outputs(p.attach.value, out)  # the figure beside the MLflow runs it shows
