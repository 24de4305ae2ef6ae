# The paper's figures (results/figures/*.{png,pdf,csv}), drawn from result files only, and the `figures` target.
# The figures of the evaluation results are drawn once the tables are (their audit gate passed); the rule files
# of the extra runs (extra.smk, probes.smk, wm.smk) add their own figures to FIGURE_TARGETS.


rule figure_main:
    input:
        results=result_files(),
        **meta_files(),
        tables=rules.build_tables.output.main_csv,  # drawn once the audit let the tables be built
        mlflow=rules.mlflow_init.output.marker,  # the figure is logged as an artifact of the runs it shows
    output:
        **figure_outputs("main", "Main results"),
    params:
        settings=S.param(S.figures_slice(SETTINGS)),
        tracking=TRACKING,
    log:
        "logs/figures/main.log",
    threads: 1
    resources:
        **job_resources("figure_main"),
    script:
        "../scripts/figure_results.py"


rule figure_ood:
    input:
        results=result_files(),
        **meta_files(),
        tables=rules.build_tables.output.main_csv,
        mlflow=rules.mlflow_init.output.marker,
    output:
        **figure_outputs("ood", "Main results"),
    params:
        settings=S.param(S.figures_slice(SETTINGS)),
        tracking=TRACKING,
    log:
        "logs/figures/ood.log",
    threads: 1
    resources:
        **job_resources("figure_ood"),
    script:
        "../scripts/figure_results.py"


rule figure_cross_dataset:
    input:
        results=result_files(),
        **meta_files(),
        tables=rules.build_tables.output.cross_csv,
        mlflow=rules.mlflow_init.output.marker,
    output:
        **figure_outputs("cross_dataset", "Main results"),
    params:
        settings=S.param(S.figures_slice(SETTINGS)),
        tracking=TRACKING,
    log:
        "logs/figures/cross_dataset.log",
    threads: 1
    resources:
        **job_resources("figure_cross_dataset"),
    script:
        "../scripts/figure_results.py"


rule figure_eda:
    input:
        **{f"eda_{d}": rules.eda.output.stats.format(dataset=d) for d in DATASETS},
    output:
        **figure_outputs("eda", "Data"),
    params:
        settings=S.param(S.figures_slice(SETTINGS)),
        tracking=TRACKING,
    log:
        "logs/figures/eda.log",
    threads: 1
    resources:
        **job_resources("figure_eda"),
    script:
        "../scripts/figure_results.py"


# `snakemake --cores 2 figures`: every figure of the profile (after the tables, which it builds first if needed), the
# probe part of the leakage audit (`audit_probes`, workflow/rules/probes.smk) and its extra part (`audit_extra`,
# workflow/rules/extra.smk); the call fails unless both reports passed and vouch for the files as they are now, e.g.
# when a probe number reached a table's source or an extra run evaluated a model trained on a test day. Like
# `tables`, a target without output: on a finished tree its own check is the one job it runs, and it regenerates
# any of its inputs that is missing.
rule figures:
    input:
        FIGURE_TARGETS,
        report=[rules.audit_probes.output.json, rules.audit_extra.output.json],
        extra_files=extra_audit_files(),
        probe_files=probe_files(),
        **AUDIT_INPUTS,
    params:
        audit=S.param(AUDIT_IDENTITY),
        target="figures",
    log:
        "logs/figures_check.log",
    threads: 1
    resources:
        **job_resources("figures"),
    script:
        "../scripts/target_gate.py"
