"""Calibrate the demand intensity u; write the record every job reads u from when config.yaml's
scenario.demand_intensity is `calibrate`, and print the value."""
import sys
from pathlib import Path

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (injected by Snakemake)

from dswm.pipeline.jobs import calibrate_job
from dswm.settings import read_param
from dswm.sim.scenario import CALIBRATE

report = calibrate_job(job=read_param(snakemake.params.settings),  # noqa: F821
                       tensor_dir=Path(snakemake.input.tensor[0]).parent, out=snakemake.output.report)  # noqa: F821
configured = snakemake.params.configured.value  # noqa: F821
use = (f"every job that reads u takes it from {snakemake.output.report}" if configured == CALIBRATE else  # noqa: F821
       f"config.yaml's scenario.demand_intensity holds {configured:g}: write this value there, or set it to "
       f"calibrate to take u from {snakemake.output.report}")  # noqa: F821
line = (f"calibrated demand_intensity = {report['demand_intensity']:.6g} (Static serves {report['served_ratio']:.4f} "
        f"on the {report['dataset']} training days, target {report['target']}); {use}")
print(line, file=sys.stderr)
print(line, file=sys.__stdout__)
