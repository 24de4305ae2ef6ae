"""Choose the shared search and the planner's open values on training days; print what config.yaml should hold."""
import sys
from pathlib import Path

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (injected by Snakemake)

from dswm.pipeline.jobs import select_job
from dswm.settings import read_param

out = Path(snakemake.output.report)  # noqa: F821
report = select_job(job=read_param(snakemake.params.settings), display=snakemake.params.display.value,  # noqa: F821
                    tensor_dir=Path(snakemake.input.tensor[0]).parent, out=out,  # noqa: F821
                    run_dir=out.parent / "model",
                    intensity=snakemake.input.get("intensity"))  # noqa: F821 (the calibrate rule's record, or None)
lines = [f"{r['search']}: served ratio {r['sr_mean']:.4f}, {r['ms_per_slot']:.1f} ms per day-slot"
         for r in report["search"]["candidates"]]
lines += [f"{report['planner']['method']} gamma={r['gamma']} sigma0={r['sigma0']}: served ratio {r['sr_mean']:.4f}"
          for r in report["planner"]["candidates"]]
lines.append(f"chosen on {', '.join(report['validation_days'])}: search = {report['search']['chosen']}; "
             f"{report['planner']['method']} planner = {report['planner']['chosen']}; write them to config.yaml")
for line in lines:
    print(line, file=sys.stderr)
    print(line, file=sys.__stdout__)
