# Calibration of the demand intensity u: Static serves the target on the calibration dataset's TRAINING days.
# With `scenario.demand_intensity: calibrate` (the default) its record is an input of every job that reads u
# (common.smk INTENSITY), which takes u from it; with a number in config.yaml no job depends on this rule.


rule calibrate:
    input:
        tensor=expand(rules.prepare.output.tensor, dataset=SETTINGS.calibration.dataset),
        meta=expand(rules.prepare.output.meta, dataset=SETTINGS.calibration.dataset),
    output:
        report=S.CALIBRATION_RECORD,
    params:
        # scenario.demand_intensity is what this job computes, never what it reads: not in its slice.
        settings=S.param(S.calibrate_slice(SETTINGS)),
        configured=S.Untracked(SETTINGS.scenario.demand_intensity),  # only for the log's last line
    log:
        "logs/calibrate.log",
    benchmark:
        "results/benchmarks/calibrate.tsv"
    threads: 1
    resources:
        **job_resources("calibrate", method=""),
    script:
        "../scripts/calibrate.py"
