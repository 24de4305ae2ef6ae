# Calibration of the demand intensity u: Static serves the target on the calibration dataset's TRAINING days.


rule calibrate:
    input:
        tensor=expand(rules.prepare.output.tensor, dataset=config["calibration"]["dataset"]),
        meta=expand(rules.prepare.output.meta, dataset=config["calibration"]["dataset"]),
    output:
        report="results/calibration/demand_intensity.json",
    params:
        calibration=config["calibration"],
        scenario={k: v for k, v in config["scenario"].items() if k != "demand_intensity"},
    log:
        "logs/calibrate.log",
    benchmark:
        "results/benchmarks/calibrate.tsv"
    script:
        "../scripts/calibrate.py"
