"""Rule prepare: raw files -> results/data/{dataset}/demand.parquet + meta.json (prep.pipeline)."""
import logging
import sys
from pathlib import Path

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (Snakemake injects `snakemake`)
logging.basicConfig(stream=sys.stderr, level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")

from dswm.settings import read_param  # noqa: E402
from prep.config import common_from_plain, dataset_from_plain  # noqa: E402
from prep.pipeline import prepare_dataset  # noqa: E402

job = read_param(snakemake.params.settings)  # noqa: F821
reference = list(snakemake.input.reference)  # noqa: F821
prepare_dataset(dataset_from_plain(job["dataset"], job["settings"]), common_from_plain(job["common"]), job["dataset"],
                raw=list(snakemake.input.raw), out_dir=Path(snakemake.output.meta).parent,  # noqa: F821
                reference_meta=reference[0] if reference else None)
