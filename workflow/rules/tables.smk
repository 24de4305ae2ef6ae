# The paper's two tables (Milan main, cross-dataset), from the per-day result files only.


rule build_tables:
    input:
        results=result_files(),
        **meta_files(),
        # The gate: tables.py writes no table unless this report passed, audits the current profile and settings
        # (params.audit) and every file it vouches for still hashes as the audit found it.
        audit=rules.audit_report.output.json,
    output:
        main_md=f"results/tables/{MAIN_DATASET}_main.md",   # Table III of tables.main_dataset (milan)
        main_tex=f"results/tables/{MAIN_DATASET}_main.tex",
        main_csv=report(f"results/tables/{MAIN_DATASET}_main.csv", caption="../report/table_main.rst",
                        category="Tables", labels={"table": "Table III", "dataset": MAIN_DATASET}),
        cross_md="results/tables/cross_dataset.md",
        cross_tex="results/tables/cross_dataset.tex",
        cross_csv=report("results/tables/cross_dataset.csv", caption="../report/table_cross.rst", category="Tables",
                         labels={"table": "Table IV", "dataset": "all"}),
        # the room a forecast could fill (tables.room), per dataset and split
        room_csv=report("results/tables/room.csv", caption="../report/table_room.rst", category="Tables",
                        labels={"table": "room a forecast could fill", "dataset": "all"}),
        # DuckDB views over the result files (no copy): `days` (every evaluated day) and `summary` (the tables'
        # numbers, from the same SQL); the paths are relative to the working directory (docs/PIPELINE.md)
        db="results/results.duckdb",
    params:
        settings=S.param(S.tables_slice(SETTINGS)),
        audit=S.param(AUDIT_IDENTITY),  # {"profile", "config_hash"} the report must carry
    log:
        "logs/tables.log",
    threads: 1
    resources:
        **job_resources("build_tables"),
    script:
        "../scripts/tables.py"


# `snakemake tables`, the default target. Snakemake checks the outputs of the rule it is asked for, but a missing
# intermediate file (a deleted days.parquet) only when a job that reads it has to run anyway; with every table newer
# than every existing input, none has, and a deleted result file would stay deleted. A targeted rule with inputs
# and no output runs on every call, first regenerating any input that is missing (and the audit and tables after
# it). Its job re-runs the gate of build_tables on the tables in place: a file the report vouches for that changed
# since, whatever its file time, fails the call and removes the tables built from it.
rule tables:
    default_target: True
    input:
        tables=list(rules.build_tables.output),
        report=rules.audit_report.output.json,
        # the exploratory statistics and figure of every dataset (paper Fig. 5 and Section V-A), part of the main job
        eda=expand(rules.eda.output, dataset=DATASETS),
        **AUDIT_INPUTS,
    params:
        audit=S.param(AUDIT_IDENTITY),
    log:
        "logs/tables_check.log",
    threads: 1
    resources:
        **job_resources("tables"),
    script:
        "../scripts/tables_check.py"


# A failed or interrupted workflow (a job that failed, Ctrl-C, SIGINT or SIGTERM to Snakemake) may have deleted files
# the tables rest on: a job's outputs are removed before it runs, and a failed job leaves none. Tables whose audit
# report no longer vouches for the files as they are (missing or changed; audits.runner.gate, without the settings'
# identity) are removed then, rather than left to be taken for current results; the next successful `snakemake
# tables` builds them again. Tables whose sources are intact are kept, whatever job failed.
onerror:
    from audits.runner import gate
    from dswm.pipeline.stale import withdraw_tables

    for _line in withdraw_tables(list(rules.build_tables.output),
                                 gate(rules.audit_report.output.json, root=Path.cwd())):
        print(_line, file=sys.stderr)
