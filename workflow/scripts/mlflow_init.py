"""Create the MLflow store (the SQLite file, or the experiment on the configured tracking server) and the experiment;
write a marker every logging rule depends on."""
import sys

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (injected by Snakemake)

from prep.atomic import write_json
from dswm.pipeline.tracking import ensure_store

info = ensure_store(snakemake.params.tracking.value)  # noqa: F821 (the mlflow section; its experiment is the slice's)
print(f"MLflow experiment {info['experiment']!r} (id {info['experiment_id']}) in {info['tracking_uri']}", file=sys.stderr)
write_json(snakemake.output.marker, info)  # noqa: F821
