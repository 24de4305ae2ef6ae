# MLflow: the SQLite store and the experiment exist before any job logs (every logging rule needs `marker`).


rule mlflow_init:
    output:
        marker="results/mlflow/experiment.json",
    params:
        settings=S.param(S.mlflow_slice(SETTINGS)),
    log:
        "logs/mlflow_init.log",
    threads: 1
    resources:
        **job_resources("mlflow_init"),
    script:
        "../scripts/mlflow_init.py"


# A run of this working directory still RUNNING when a workflow starts belongs to a job killed with SIGKILL
# (Snakemake's lock keeps two workflows out of one working directory): it is ended KILLED here, so the store never
# shows a run as live that nothing is running. Runs of interrupted jobs that got SIGTERM or SIGINT are ended FAILED
# by the job itself. On a shared tracking server, other working directories' runs are left alone.
onstart:
    from dswm.config import to_plain
    from dswm.pipeline.tracking import close_orphans

    _closed = close_orphans(mlflow_cfg=to_plain(SETTINGS.mlflow))
    if _closed:
        print(f"MLflow: {_closed} run(s) left RUNNING by an earlier, killed workflow are now KILLED", file=sys.stderr)
