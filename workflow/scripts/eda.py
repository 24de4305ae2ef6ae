"""Rule eda: exploratory statistics (JSON) and the EDA figure (PNG) of one prepared dataset (prep.eda)."""
import logging
import sys
from pathlib import Path

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (Snakemake injects `snakemake`)
logging.basicConfig(stream=sys.stderr, level=logging.INFO, format="%(asctime)s %(name)s %(levelname)s %(message)s")

from dswm.settings import read_param  # noqa: E402
from prep.eda import run_eda  # noqa: E402
from prep.tensor import load  # noqa: E402

job = read_param(snakemake.params.settings)  # noqa: F821
summary = run_eda(load(Path(snakemake.input.meta).parent), json_path=snakemake.output.stats,  # noqa: F821
                  png_path=snakemake.output.figure, top_frac=float(job["top_share_frac"]))  # noqa: F821
logging.info("eda %s: zero_cell_rate=%.4f top5_share=%.4f hotspot_overlap_04h_14h=%.2f", summary["dataset"],
             summary["zero_cell_rate"], summary["top5_share"], summary["hotspot_overlap_04h_14h"])
mig = summary["hotspot_migration"]
logging.info("eda %s: hotspot migration on %s slots %d..%d (%s): top-%d share overlap %d slots apart %s, "
             "energy outside the first singular component %s", summary["dataset"], mig["window"]["day"],
             mig["window"]["first_slot"], mig["window"]["first_slot"] + mig["window"]["slots"] - 1,
             mig["window"]["basis"], mig["top_k"], mig["lag_slots"], mig["top_k_share_overlap"],
             mig["energy_outside_first_component"])
