"""Paper Figs. 14-16 and the trajectories of Section V-K (results/figures/qualitative_<kind>.{png,pdf,csv})."""
import sys
from pathlib import Path

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (injected by Snakemake)

from dswm.figures import qualitative as q
from dswm.settings import read_param

inp, p = snakemake.input, snakemake.params  # noqa: F821
out = {k: getattr(snakemake.output, k) for k in ("png", "pdf", "csv")}  # noqa: F821
if p.kind == "milan":
    q.milan_figure(maps=inp.maps, meta=inp.meta, grid=inp.grid, totals=inp.totals, profile=p.profile, out=out)
elif p.kind == "trajectories":
    q.trajectories_figure(trajectories=inp.trajectories, methods=p.methods, labels=p.labels,
                          tensor_dir=Path(inp.tensor).parent, profile=p.profile, out=out)
else:
    q.region_figure(dataset=p.kind, settings=read_param(p.settings), raw=list(inp.raw),
                    tensor_dir=Path(inp.tensor).parent, profile=p.profile, out=out)

from dswm.pipeline.tracking import attach_figure_outputs  # noqa: E402

attach_figure_outputs(p.attach.value, out)  # the figure beside the MLflow runs it shows
