"""Figure room_fill: the share of the room each planner fills in one regime (results/figures/room_fill.*)."""
import json
import sys
from pathlib import Path

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (injected by Snakemake)

import polars as pl

from dswm.figures.room_fill import draw_room_fill, room_fill_table

inp, p = snakemake.input, snakemake.params  # noqa: F821
out = {k: getattr(snakemake.output, k) for k in ("png", "pdf", "csv")}  # noqa: F821
runs = pl.concat([pl.read_parquet(f).with_columns(pl.lit(Path(f).parts[-3]).alias("arm")) for f in inp.runs],
                 how="diagonal_relaxed")  # results/extra/<dataset>/room_fill/<arm>/seed<seed>/days.parquet
table = room_fill_table(runs, arms=p.arms, labels=p.labels, regime=p.regime, split_labels=p.split_labels)
draw_room_fill(table, [json.loads(Path(f).read_text()) for f in inp.fits], profile=p.profile,
               source=",".join(sorted(set(runs["data_source"]))), out=out)

from dswm.pipeline.tracking import attach_figure_outputs  # noqa: E402

attach_figure_outputs(p.attach.value, out)  # the figure beside the MLflow runs it shows
