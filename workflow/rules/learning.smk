# The learning curves (`snakemake --cores 2 learning`; config.yaml `learning`, dswm.settings.learning): ONE run per
# learner of learning.methods (those in methods.run that the train rule fits) on learning.dataset with learning.seed,
# at its cap (its profile's budget with learning.caps.<method> merged over it), trained on the TRAINING days less
# the last learning.validation_days; its untrained model and its snapshots at the learning.ladder fractions of the
# cap are scored on those held-out days (dswm.protocol.learning: never a test day), and so are the reference methods
# (learning.references: Static and Greedy), in the evaluation's own environment and initial fleet. Outputs under
# results/learning/: never a table's source; `tables` schedules none of these jobs.
try:  # a bad section stops every target here, as a bad key of any other section does
    LEARNING = S.learning_settings(config, PROFILE)
    """config.yaml `learning` merged with `learning.budgets.<profile>` (not part of SETTINGS: no main slice
    changes)."""
    S.check_learning(SETTINGS, LEARNING)
except ConfigError as err:
    raise WorkflowError(CONFIG_SOURCES.relabel(str(err))) from None
LEARNERS = S.learning_methods(SETTINGS, LEARNING)
LEARNING_REFERENCES = S.learning_references(SETTINGS, LEARNING)
LEARNING_RUN = "results/learning/{dataset}/{method}/seed{seed}"


rule learning_train:
    input:
        tensor=rules.prepare.output.tensor,
        meta=rules.prepare.output.meta,
        mlflow=rules.mlflow_init.output.marker,
        **INTENSITY,  # the calibrate rule's record when scenario.demand_intensity is `calibrate`
    output:
        model=LEARNING_RUN + "/model.pt",
        manifest=LEARNING_RUN + "/train_manifest.json",
        history=LEARNING_RUN + "/train_history.parquet",  # the training return drawn beside the curve
        snapshots=directory(LEARNING_RUN + "/snapshots"),  # the untrained model and the ladder, with index.json
    params:
        settings=lambda wc: S.param(S.learning_train_slice(SETTINGS, LEARNING, wc.method)),
        tracking=TRACKING,
        run_dir=lambda wc: LEARNING_RUN.format(**dict(wc.items())) + "/train",
    log:
        "logs/learning_train/{dataset}/{method}/seed{seed}.log",
    benchmark:
        "results/benchmarks/learning_train/{dataset}/{method}/seed{seed}.tsv"
    wildcard_constraints:
        method=_alternatives(LEARNERS),
    threads: 1
    priority: learning_priority
    resources:
        **job_resources("learning_train", method="{method}"),
    script:
        "../scripts/learning_train.py"


rule learning_score:
    input:
        unpack(learning_snapshots),
        tensor=rules.prepare.output.tensor,
        meta=rules.prepare.output.meta,
        mlflow=rules.mlflow_init.output.marker,
        **INTENSITY,  # the calibrate rule's record when scenario.demand_intensity is `calibrate`
    output:
        curve=LEARNING_RUN + "/curve.parquet",
    params:
        settings=lambda wc: S.param(S.learning_score_slice(SETTINGS, LEARNING, wc.method)),
        tracking=TRACKING,
        display=S.Untracked(DISPLAY),
    log:
        "logs/learning_score/{dataset}/{method}/seed{seed}.log",
    benchmark:
        "results/benchmarks/learning_score/{dataset}/{method}/seed{seed}.tsv"
    wildcard_constraints:
        method=_alternatives(LEARNERS + LEARNING_REFERENCES),
    threads: 1
    priority: learning_priority
    resources:
        **job_resources("learning_score", method="{method}"),
    script:
        "../scripts/learning_score.py"


rule figure_learning_curves:
    input:
        curves=learning_files(rules.learning_score.output.curve, LEARNERS),
        references=learning_files(rules.learning_score.output.curve, LEARNING_REFERENCES),
        histories=learning_files(rules.learning_train.output.history, LEARNERS),
        meta=rules.prepare.output.meta.format(dataset=LEARNING.dataset),
        mlflow=rules.mlflow_init.output.marker,  # the figure is logged beside its runs
    output:
        png=report(f"{FIGURE_DIR}/learning_curves.png", caption="../report/learning_curves.rst",
                   category="Learning curves", labels={"figure": "learning_curves"}),
        pdf=f"{FIGURE_DIR}/learning_curves.pdf",
        csv=report(f"{FIGURE_DIR}/learning_curves.csv", caption="../report/learning_curves.rst",
                   category="Learning curves", labels={"figure": "learning_curves", "file": "data (CSV)"}),
        verdict=report(f"{FIGURE_DIR}/learning_verdict.csv", caption="../report/learning_curves.rst",
                       category="Learning curves", labels={"figure": "learning_curves", "file": "verdict (CSV)"}),
    params:
        attach=figure_attach(["learning"], [LEARNING.dataset], LEARNERS + LEARNING_REFERENCES),
        profile=PROFILE,
        methods=LEARNERS,
        labels={m: SETTINGS.methods[m].label for m in LEARNERS},
        ladder=list(LEARNING.ladder),
    log:
        "logs/figures/learning_curves.log",
    benchmark:
        "results/benchmarks/figures/learning_curves.tsv"
    threads: 1
    resources:
        **job_resources("figure_learning_curves"),
    script:
        "../scripts/figure_learning_curves.py"


# The learning part of the leakage audit (audits.runner.SCOPES["learning"]: protocol.learning_days over the runs under
# results/learning/), its own report whatever the verdict; the `learning` target passes only when it passed.
rule audit_learning:
    input:
        learning_audit_files(),
        meta=rules.prepare.output.meta.format(dataset=LEARNING.dataset),
    output:
        json=LEARNING_AUDIT["json"],
        md=report(LEARNING_AUDIT["md"], caption="../report/audit_learning.rst", category="Leakage audit",
                  labels={"report": "learning audit"}),
    params:
        settings=AUDIT_SETTINGS,
        configfiles=S.Untracked([str(f) for f in workflow.configfiles]),
        scope="learning",
    log:
        "logs/audit/learning.log",
    threads: 1
    resources:
        **job_resources("audit_learning"),
    script:
        "../scripts/audit.py"


# The target: the learning curves (not part of `tables` or `figures`), and the learning audit; the call fails unless
# that report passed and vouches for the learning runs' files as they are now. A target without output: on a finished
# tree its own check is the one job it runs.
rule learning:
    input:
        rules.figure_learning_curves.output,
        report=rules.audit_learning.output.json,
        runs=learning_audit_files(),
    params:
        audit=S.param(AUDIT_IDENTITY),
        target="learning",
    log:
        "logs/learning_check.log",
    threads: 1
    resources:
        **job_resources("learning"),
    script:
        "../scripts/target_gate.py"
