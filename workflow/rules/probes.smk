# The sample-efficiency probe behind paper Fig. 9 and that figure. The main `train` jobs of (figures.dataset, a
# method of figures.sample_efficiency.methods that the train rule fits, a seed of figures.seeds) save model snapshots
# at figures.sample_efficiency.fractions of their fixed budget (their `snapshots` output; dswm.settings.probe_jobs);
# the `probe` rule evaluates each on ONE fixed test day (the first ID test day) in the evaluation's environment, no
# early stopping, no model selection. Outputs under results/probes/: never a table's source, and the audit proves
# that no probe number reached one (protocol.probes_out_of_tables, in the `audit_probes` report below).
# Each probe row records the job's evaluated value on that day, so the audit tells the evaluation's own number (the
# trained model's, as a rule) from a probe number. figures.seeds are seeds the profile runs (checked in extra.smk).
PROBE_JOBS = S.probe_jobs(SETTINGS)
"""Every (dataset, method, seed) the probe evaluates."""
PROBE_METHODS = S.probed_methods(SETTINGS)
PROBE_DIR = "results/probes/{dataset}/{method}/seed{seed}"


rule probe:
    input:
        snapshots=rules.train.output.snapshots,  # the model snapshots of the same (dataset, method, seed)
        evaluation=rules.evaluate.output.days,  # its evaluation: the value recorded beside each probe value
        tensor=rules.prepare.output.tensor,
        meta=rules.prepare.output.meta,
        mlflow=rules.mlflow_init.output.marker,
        **INTENSITY,  # the calibrate rule's record when scenario.demand_intensity is `calibrate`
    output:
        probe=PROBE_DIR + "/probe.parquet",
        record=PROBE_DIR + "/probe_manifest.json",  # SHA-256 and size of the probe file, written last
    params:
        settings=lambda wc: S.param(S.probe_slice(SETTINGS, wc.method)),
        tracking=TRACKING,
        display=S.Untracked(DISPLAY),
    log:
        "logs/probe/{dataset}/{method}/seed{seed}.log",
    benchmark:
        "results/benchmarks/probe/{dataset}/{method}/seed{seed}.tsv"
    wildcard_constraints:
        method="|".join(PROBE_METHODS) or "(?!)",
    threads: 1
    resources:
        **job_resources("probe", method="{method}"),
    script:
        "../scripts/probe.py"


# The probe part of the leakage audit (audits.runner.SCOPES["probes"]: protocol.probes_out_of_tables over the probe
# files and the tables' sources), its own report whatever the verdict; the `figures` target passes only when it
# passed. The main audit (`audit_report`) leaves the probe files out, so that its inputs stay those of `tables`.
rule audit_probes:
    input:
        probes=probe_files(),
        results=result_files(),  # the tables' sources, which no probe number may reach
    output:
        json=PROBE_AUDIT["json"],
        md=report(PROBE_AUDIT["md"], caption="../report/audit_probes.rst", category="Leakage audit",
                  labels={"report": "probe audit"}),
    params:
        settings=AUDIT_SETTINGS,
        configfiles=S.Untracked([str(f) for f in workflow.configfiles]),
        scope="probes",
    log:
        "logs/audit/probes.log",
    threads: 1
    resources:
        **job_resources("audit_probes"),
    script:
        "../scripts/audit.py"


rule figure_sample_efficiency:
    input:
        probes=probe_files(),
        meta=rules.prepare.output.meta.format(dataset=FIGURES_SETTINGS.dataset),
        mlflow=rules.mlflow_init.output.marker,  # the figure is logged beside its runs
    output:
        **figure_outputs("sample_efficiency", "Sample efficiency"),
    params:
        attach=figure_attach(["train", "probe"], [FIGURES_SETTINGS.dataset], PROBE_METHODS),
        profile=PROFILE,
        methods=PROBE_METHODS,
        labels={m: SETTINGS.methods[m].label for m in PROBE_METHODS},
        fractions=list(FIGURES_SETTINGS.sample_efficiency.fractions),
    log:
        "logs/figures/sample_efficiency.log",
    benchmark:
        "results/benchmarks/figures/sample_efficiency.tsv"
    threads: 1
    resources:
        **job_resources("figure_sample_efficiency"),
    script:
        "../scripts/figure_sample_efficiency.py"
