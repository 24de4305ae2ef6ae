# Settings the paper leaves open, chosen on the TRAINING days of one dataset (never on test days): the shared
# BCD search's strength and the planner's gamma and sigma0. Not part of `tables`: config.yaml keeps the values.


rule select:
    input:
        tensor=expand(rules.prepare.output.tensor, dataset=SETTINGS.selection.dataset),
        meta=expand(rules.prepare.output.meta, dataset=SETTINGS.selection.dataset),
        **INTENSITY,  # the calibrate rule's record when scenario.demand_intensity is `calibrate`
    output:
        report="results/selection/selection.json",
    params:
        # built when a `select` job is: a config without `selection.planner_method` in methods.run (the README's own
        # method) runs every other target, and `select` alone stops with the message
        settings=lambda wc: S.param(with_source(S.select_slice, SETTINGS)),
        display=S.Untracked(DISPLAY),
    log:
        "logs/select.log",
    benchmark:
        "results/benchmarks/select.tsv"
    threads: 1
    resources:
        **job_resources("select", method=SETTINGS.selection.planner_method),
    script:
        "../scripts/select.py"
