# Leakage audit (docs/PROTOCOL.md §4-§6, paper Sections I and V-B): read-only checks of the splits, the training
# statistics and the protocol, from the files alone. `audit_report` writes the report whatever the verdict; the
# tables rule builds no table unless that report passed, audits the current profile and settings, and every file it
# vouches for is unchanged. Its inputs are the tables' sources only: the probe files that `figures` writes are
# audited apart (`audit_probes`, workflow/rules/probes.smk), so a finished tree stays up to date for `tables` after
# `figures`. `audit` (a target with no output, so Snakemake runs it on every call) audits the tree afresh, both
# parts, rewrites their reports and fails when any check fails.
from audits.runner import report_identity

AUDIT_SETTINGS = S.param(S.audit_slice(SETTINGS))
"""The settings the audit runs under (every setting but the display and selection ones): its rerun trigger."""
AUDIT_IDENTITY = report_identity(SETTINGS)
"""{"profile", "config_hash"} a report of the audit under the current settings carries (the tables gate's check)."""
PROBE_AUDIT = {"json": "results/audit/probes.json", "md": "results/audit/probes.md"}
"""The report of the probe part of the audit (the `audit_probes` rule's outputs, rewritten by `audit`)."""
LEARNING_AUDIT = {"json": "results/audit/learning.json", "md": "results/audit/learning.md"}
"""The report of the learning part of the audit (the `audit_learning` rule's outputs, rewritten by `audit`)."""
EXTRA_AUDIT = {"json": "results/audit/extra.json", "md": "results/audit/extra.md"}
"""The report of the extra part of the audit (the `audit_extra` rule's outputs, rewritten by `audit`)."""
AUDIT_INPUTS = dict(
    raw=[p for d in DATASETS for p in raw_files(d)],
    tensors=expand(rules.prepare.output.tensor, dataset=DATASETS),
    metas=expand(rules.prepare.output.meta, dataset=DATASETS),
    results=result_files(),
    trajectories=[rules.evaluate.output.trajectory.format(dataset=d, method=m, seed=s)
                  for d, m, s in SETTINGS.jobs()],
    records=[rules.evaluate.output.record.format(dataset=d, method=m, seed=s) for d, m, s in SETTINGS.jobs()],
    manifests=train_manifests(),
    models=[rules.train.output.model.format(dataset=d, method=m, seed=s) for d, m, s in SETTINGS.jobs()
            if m in TRAINED],
    # The calibration record: the source of u when scenario.demand_intensity is `calibrate` (always an input
    # then); with a number in config.yaml it is optional (calibrate runs by hand), but the audit checks it when
    # present: declared then, so a run of calibrate finishes before the audit reads it and a new record
    # re-audits.
    calibration=lambda wildcards: [p for p in rules.calibrate.output if INTENSITY or Path(p).exists()],
)
"""Every file the audit reads that a rule writes: the inputs of `audit_report`, `audit` and the `tables` target."""


rule audit_report:
    input:
        **AUDIT_INPUTS,
    output:
        json="results/audit/report.json",
        md=report("results/audit/report.md", caption="../report/audit.rst", category="Leakage audit",
                  labels={"report": "audit"}),
    params:
        settings=AUDIT_SETTINGS,
        configfiles=S.Untracked([str(f) for f in workflow.configfiles]),
        scope="tables",  # audits.runner.SCOPES: every check, over the tables' sources (no probe file)
    log:
        "logs/audit/report.log",
    benchmark:
        "results/benchmarks/audit/report.tsv"
    threads: 1
    resources:
        **job_resources("audit_report"),
    script:
        "../scripts/audit.py"


# No output: Snakemake runs a targeted rule without output on every call (`snakemake audit` runs this one job and
# nothing else on a finished tree), first regenerating any of its inputs that is missing. It runs the whole audit
# itself (its inputs are what the audit reads, not the reports, so the audit runs once): the tables' part, rewriting
# results/audit/report.{json,md}; where the sample-efficiency probe's files exist (after `figures`), the probe
# part, rewriting results/audit/probes.{json,md}; where the figures' extra runs exist (after `figures`), the extra
# part, rewriting results/audit/extra.{json,md}; and where learning runs exist (after `learning`), the learning
# part, rewriting results/audit/learning.{json,md}.
rule audit:
    input:
        **AUDIT_INPUTS,
        # optional as the calibration record: the probe files present (workflow/rules/probes.smk)
        probes=lambda wildcards: [p for p in probe_files() if Path(p).exists()],
        # ... and the learning runs' files present (workflow/rules/learning.smk)
        learning=lambda wildcards: [p for p in learning_audit_files() if Path(p).exists()],
        # ... and the figures' extra runs' files present (workflow/rules/extra.smk)
        extra=lambda wildcards: [p for p in extra_audit_files() if Path(p).exists()],
    params:
        settings=AUDIT_SETTINGS,
        configfiles=S.Untracked([str(f) for f in workflow.configfiles]),
        json=rules.audit_report.output.json,
        md=rules.audit_report.output.md,
        probes_json=PROBE_AUDIT["json"],
        probes_md=PROBE_AUDIT["md"],
        learning_json=LEARNING_AUDIT["json"],
        learning_md=LEARNING_AUDIT["md"],
        extra_json=EXTRA_AUDIT["json"],
        extra_md=EXTRA_AUDIT["md"],
        extra_runs=lambda wildcards: extra_audit_runs(),  # workflow/rules/extra.smk
    log:
        "logs/audit/audit.log",
    threads: 1
    resources:
        **job_resources("audit"),
    script:
        "../scripts/audit.py"
