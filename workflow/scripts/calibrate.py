"""Calibrate the demand intensity u; print it (config.yaml's scenario.demand_intensity keeps the value)."""
import sys
from pathlib import Path

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (injected by Snakemake)

from dswm.pipeline.jobs import calibrate_job
from dswm.settings import read_param

report = calibrate_job(job=read_param(snakemake.params.settings),  # noqa: F821
                       tensor_dir=Path(snakemake.input.tensor[0]).parent, out=snakemake.output.report)  # noqa: F821
line = (f"calibrated demand_intensity = {report['demand_intensity']:.6g} (Static serves {report['served_ratio']:.4f} "
        f"on the {report['dataset']} training days, target {report['target']}); write it to config.yaml's "
        f"scenario.demand_intensity")
print(line, file=sys.stderr)
print(line, file=sys.__stdout__)
