# The paper's two tables (Milan main, cross-dataset), from the per-day result files only.


rule tables:
    default_target: True
    input:
        results=result_files(),
        **meta_files(),
        audit=rules.audit.output.passed,  # no table from a pipeline that fails the leakage audit
    output:
        milan_md="results/tables/milan_main.md",
        milan_tex="results/tables/milan_main.tex",
        milan_csv="results/tables/milan_main.csv",
        cross_md="results/tables/cross_dataset.md",
        cross_tex="results/tables/cross_dataset.tex",
        cross_csv="results/tables/cross_dataset.csv",
    params:
        profile=PROFILE,
        tables=config["tables"],
        methods=METHODS,
        datasets=DATASETS,
    log:
        "logs/tables.log",
    script:
        "../scripts/tables.py"
