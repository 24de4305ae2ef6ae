# Training of learning methods on the TRAINING days of a dataset (never its test days). Only training sources
# are trained (common.smk TRAINED): a method whose training is identical to an earlier one's evaluates its model.


rule train:
    input:
        tensor=rules.prepare.output.tensor,
        meta=rules.prepare.output.meta,
        mlflow=rules.mlflow_init.output.marker,
        **INTENSITY,  # the calibrate rule's record when scenario.demand_intensity is `calibrate`
    output:
        model="results/{dataset}/{method}/seed{seed}/model.pt",
        manifest="results/{dataset}/{method}/seed{seed}/train_manifest.json",
        # The loss history (what MLflow also receives), the source of the training-diagnostics figure.
        history="results/{dataset}/{method}/seed{seed}/train_history.parquet",
        # Model snapshots at figures.sample_efficiency.fractions of the budget with their index.json, for the jobs
        # of the sample-efficiency probe (dswm.settings.probe_jobs); empty for every other job.
        snapshots=directory("results/{dataset}/{method}/seed{seed}/snapshots"),
    params:
        settings=lambda wc: S.param(S.train_slice(SETTINGS, wc.method, wc.dataset, int(wc.seed))),
        tracking=TRACKING,
        evaluated_as=lambda wc: S.Untracked(S.evaluated_as(SETTINGS, wc.method)),
        run_dir=lambda wc: f"results/{wc.dataset}/{wc.method}/seed{wc.seed}/train",
    log:
        "logs/train/{dataset}/{method}/seed{seed}.log",
    benchmark:
        "results/benchmarks/train/{dataset}/{method}/seed{seed}.tsv"
    wildcard_constraints:
        method=TRAINED_PATTERN,
    threads: 1
    priority: start_priority  # resources.start_order
    resources:
        **job_resources("train", method="{method}"),
    script:
        "../scripts/train.py"
