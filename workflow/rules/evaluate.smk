# Evaluation of one (dataset, method, seed) on the fixed ID and OOD days in the shared environment.


rule evaluate:
    input:
        unpack(trained_model),
        tensor=rules.prepare.output.tensor,
        meta=rules.prepare.output.meta,
        mlflow=rules.mlflow_init.output.marker,
    output:
        days="results/{dataset}/{method}/seed{seed}/days.parquet",
        trajectory="results/{dataset}/{method}/seed{seed}/trajectory.npz",
    params:
        settings=lambda wc: S.param(S.evaluate_slice(SETTINGS, wc.method)),
        display=S.Untracked(DISPLAY),
    log:
        "logs/evaluate/{dataset}/{method}/seed{seed}.log",
    benchmark:
        "results/benchmarks/evaluate/{dataset}/{method}/seed{seed}.tsv"
    threads: 1
    script:
        "../scripts/evaluate.py"
