"""Calibrate the demand intensity u; print it (config.yaml's scenario.demand_intensity keeps the value)."""
import sys
from pathlib import Path

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (injected by Snakemake)

from dswm.jobs import calibrate_job

report = calibrate_job(config=snakemake.config, tensor_dir=Path(snakemake.input.tensor[0]).parent,  # noqa: F821
                       out=snakemake.output.report)  # noqa: F821
line = (f"calibrated demand_intensity = {report['demand_intensity']:.6g} (Static serves {report['served_ratio']:.4f} "
        f"on the {report['dataset']} training days, target {report['target']}; config.yaml has "
        f"{report['config_value']:.6g})")
print(line, file=sys.stderr)
print(line, file=sys.__stdout__)
