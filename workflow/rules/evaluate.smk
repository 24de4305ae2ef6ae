# Evaluation of one (dataset, method, seed) on the fixed ID and OOD days in the shared environment.


rule evaluate:
    input:
        unpack(trained_model),
        unpack(reused_evaluation),  # the first seed's evaluation, for a method the seed does not change
        tensor=rules.prepare.output.tensor,
        meta=rules.prepare.output.meta,
        mlflow=rules.mlflow_init.output.marker,
        **INTENSITY,  # the calibrate rule's record when scenario.demand_intensity is `calibrate`
    output:
        days="results/{dataset}/{method}/seed{seed}/days.parquet",
        trajectory="results/{dataset}/{method}/seed{seed}/trajectory.npz",
        # The content record (SHA-256 and size of the two files above), written last: the audit checks every
        # result file against it, whatever its file time says.
        record="results/{dataset}/{method}/seed{seed}/eval_manifest.json",
    params:
        settings=lambda wc: S.param(S.evaluate_slice(SETTINGS, wc.method)),
        tracking=TRACKING,
        display=S.Untracked(DISPLAY),
    log:
        "logs/evaluate/{dataset}/{method}/seed{seed}.log",
    benchmark:
        "results/benchmarks/evaluate/{dataset}/{method}/seed{seed}.tsv"
    threads: 1
    priority: start_priority  # resources.start_order
    resources:
        **job_resources("evaluate", method="{method}"),
    script:
        "../scripts/evaluate.py"
