# MLflow: the SQLite store and the experiment exist before any job logs (every logging rule needs `marker`).


rule mlflow_init:
    output:
        marker="results/mlflow/experiment.json",
    params:
        store=config["mlflow"]["store"],
        artifacts=config["mlflow"]["artifacts"],
        experiment=config["mlflow"]["experiment"],
    log:
        "logs/mlflow_init.log",
    script:
        "../scripts/mlflow_init.py"
