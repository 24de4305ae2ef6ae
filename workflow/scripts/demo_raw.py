"""Rule demo_raw: writes one dataset's demo raw files in the published format (prep.demo)."""
import logging
import sys

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (Snakemake injects `snakemake`)
logging.basicConfig(stream=sys.stderr, level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")

from prep.pipeline import generate_demo  # noqa: E402

generate_demo(snakemake.config, snakemake.wildcards.dataset, snakemake.output.raw)  # noqa: F821
