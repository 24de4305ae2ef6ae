"""Figure headroom: Perfect - Greedy and Ceiling - Perfect over D_max x u (results/figures/headroom.{png,pdf,csv})."""
import sys

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (injected by Snakemake)

from dswm.figures.common import read_days
from dswm.figures.headroom import draw_headroom, headroom_table
from dswm.protocol.tables import DATASET_LABELS
from dswm.settings import EvalDayLimits

inp, p = snakemake.input, snakemake.params  # noqa: F821
out = {k: getattr(snakemake.output, k) for k in ("png", "pdf", "csv")}  # noqa: F821
main = read_days(inp.main)
table = headroom_table(main, read_days(inp.runs) if inp.runs else None, datasets=p.datasets, d_max_m=p.d_max_m,
                       intensity_scales=p.intensity_scales, own_d_max=p.own_d_max, seeds=p.seeds,
                       limits=EvalDayLimits(**p.eval_days), min_room=p.min_room,
                       names={(float(d), float(f)): name for d, f, name in p.names})
draw_headroom(table, min_room=p.min_room, dataset_labels=DATASET_LABELS, profile=p.profile,
              source=",".join(sorted(set(main["data_source"]))), out=out)

from dswm.pipeline.tracking import attach_figure_outputs  # noqa: E402

attach_figure_outputs(p.attach.value, out)  # the figure beside the MLflow runs it shows
