"""Paper Fig. 10: served ratio against fleet size and demand intensity (results/figures/scaling.{png,pdf,csv})."""
import sys

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (injected by Snakemake)

from dswm.figures.common import read_days
from dswm.figures.scaling import draw_scaling, scaling_days
from dswm.settings import EvalDayLimits

inp, p = snakemake.input, snakemake.params  # noqa: F821
out = {k: getattr(snakemake.output, k) for k in ("png", "pdf", "csv")}  # noqa: F821
main = read_days(inp.reference)
days = scaling_days(main, read_days(inp.runs) if inp.runs else None, methods=p.methods, seeds=p.seeds,
                    limits=EvalDayLimits(**p.eval_days), n_uavs=p.n_uavs, fleet_sizes=p.fleet_sizes,
                    intensity_scales=p.intensity_scales)
draw_scaling(days, order=p.methods, labels=p.labels, split_labels=p.split_labels,
             reference={"K": p.n_uavs, "u": 1.0}, profile=p.profile,
             source=",".join(sorted(set(main["data_source"]))), out=out)

from dswm.pipeline.tracking import attach_figure_outputs  # noqa: E402

attach_figure_outputs(p.attach.value, out)  # the figure beside the MLflow runs it shows
