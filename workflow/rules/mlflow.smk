# MLflow: the SQLite store and the experiment exist before any job logs (every logging rule needs `marker`).


rule mlflow_init:
    output:
        marker="results/mlflow/experiment.json",
    params:
        settings=S.param(S.mlflow_slice(SETTINGS)),
    log:
        "logs/mlflow_init.log",
    script:
        "../scripts/mlflow_init.py"
