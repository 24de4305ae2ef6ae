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
# Before that, a SQLite store copied or moved with its tree (`cp -a`) is made this tree's own: its artifact location
# and the paths of its runs still name the tree it came from (dswm.pipeline.tracking.adopt_store).
onstart:
    from dswm.config import to_plain
    from dswm.pipeline.tracking import start_workflow

    for _line in start_workflow(to_plain(SETTINGS.mlflow)):
        print(f"MLflow: {_line}", file=sys.stderr)
