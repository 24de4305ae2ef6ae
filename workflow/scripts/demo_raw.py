"""Rule demo_raw: writes one dataset's demo raw files in the published format (prep.demo)."""
import logging
import sys

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (Snakemake injects `snakemake`)
logging.basicConfig(stream=sys.stderr, level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")

from dswm.settings import read_param  # noqa: E402
from prep.config import dataset_from_plain  # noqa: E402
from prep.pipeline import generate_demo  # noqa: E402

job = read_param(snakemake.params.settings)  # noqa: F821
generate_demo(dataset_from_plain(job["dataset"], job["settings"]), job["dataset"], snakemake.output.raw)  # noqa: F821
