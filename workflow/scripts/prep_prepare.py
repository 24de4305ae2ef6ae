"""Rule prepare: raw files -> results/data/{dataset}/demand.parquet + meta.json (prep.pipeline)."""
import logging
import sys
from pathlib import Path

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (Snakemake injects `snakemake`)
logging.basicConfig(stream=sys.stderr, level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")

from prep.pipeline import prepare_dataset  # noqa: E402

reference = list(snakemake.input.reference)  # noqa: F821
prepare_dataset(snakemake.config, snakemake.wildcards.dataset, raw=list(snakemake.input.raw),  # noqa: F821
                out_dir=Path(snakemake.output.meta).parent, reference_meta=reference[0] if reference else None)  # noqa: F821
