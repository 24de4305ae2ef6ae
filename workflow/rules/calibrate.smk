# Calibration of the demand intensity u: Static serves the target on the calibration dataset's TRAINING days.


rule calibrate:
    input:
        tensor=expand(rules.prepare.output.tensor, dataset=SETTINGS.calibration.dataset),
        meta=expand(rules.prepare.output.meta, dataset=SETTINGS.calibration.dataset),
    output:
        report="results/calibration/demand_intensity.json",
    params:
        # scenario.demand_intensity is what this job computes: writing its value back reruns nothing.
        settings=S.param(S.calibrate_slice(SETTINGS)),
    log:
        "logs/calibrate.log",
    benchmark:
        "results/benchmarks/calibrate.tsv"
    script:
        "../scripts/calibrate.py"
