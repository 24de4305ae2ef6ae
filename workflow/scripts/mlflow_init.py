"""Create the MLflow SQLite store and the experiment; write a marker every logging rule depends on."""
import sys

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (injected by Snakemake)

from dswm.atomic import write_json
from dswm.tracking import init_store

p = snakemake.params  # noqa: F821
info = init_store(store=p.store, artifacts=p.artifacts, experiment=p.experiment)
print(f"MLflow experiment {info['experiment']!r} (id {info['experiment_id']}) in {info['tracking_uri']}", file=sys.stderr)
write_json(snakemake.output.marker, info)  # noqa: F821
