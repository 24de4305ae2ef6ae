# MLflow: the SQLite store and the experiment exist before any job logs (every logging rule needs `marker`).


rule mlflow_init:
    output:
        marker="results/mlflow/experiment.json",
    params:
        settings=S.param(S.mlflow_slice(SETTINGS)),  # the experiment's name: a new one reruns every logging job
        tracking=TRACKING,  # where the store is and how a server is asked: reruns nothing (see onstart)
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
# A SQLite store copied or moved with its tree (`cp -a`) is made this tree's own first: its artifact location and the
# paths of its runs still name the tree it came from (dswm.pipeline.tracking.adopt_store).
# `mlflow_init` does not rerun when the store, the server or the artifact location change (a result does not depend
# on where its run is logged), so before any job starts, the store and the experiments of the current settings are
# made to exist here (idempotent) once `mlflow_init` has run; a job that logs then finds them wherever they now are.
# The one onstart handler of the workflow also checks, first, that every output directory can be written.
onstart:
    from dswm.pipeline.tracking import ensure_store, start_workflow

    check_outputs_writable()

    for _line in start_workflow(TRACKING.value):  # adopt a copied store, then close orphaned runs
        print(f"MLflow: {_line}", file=sys.stderr)
    if Path(rules.mlflow_init.output.marker).exists():  # else mlflow_init creates them before any job logs
        ensure_store(TRACKING.value)
