# The paper's two tables (Milan main, cross-dataset), from the per-day result files only.


rule tables:
    default_target: True
    input:
        results=result_files(),
        **meta_files(),
        audit=rules.audit.output.passed,  # no table from a pipeline that fails the leakage audit
    output:
        main_md=f"results/tables/{MAIN_DATASET}_main.md",   # Table III of tables.main_dataset (milan)
        main_tex=f"results/tables/{MAIN_DATASET}_main.tex",
        main_csv=f"results/tables/{MAIN_DATASET}_main.csv",
        cross_md="results/tables/cross_dataset.md",
        cross_tex="results/tables/cross_dataset.tex",
        cross_csv="results/tables/cross_dataset.csv",
        room_csv="results/tables/room.csv",  # the room a forecast could fill (tables.room), per dataset and split
    params:
        settings=S.param(S.tables_slice(SETTINGS)),
    log:
        "logs/tables.log",
    script:
        "../scripts/tables.py"
