# Leakage audit (docs/PROTOCOL.md §4-§6, paper Sections I and V-B): read-only checks of the splits, the training
# statistics and the protocol, from the files alone. `audit_report` writes the report whatever the verdict;
# `audit` passes only when every check passes, and its `passed` file is what the tables rule requires.


rule audit_report:
    input:
        raw=[p for d in DATASETS for p in raw_files(d)],
        tensors=expand(rules.prepare.output.tensor, dataset=DATASETS),
        metas=expand(rules.prepare.output.meta, dataset=DATASETS),
        results=result_files(),
        trajectories=[rules.evaluate.output.trajectory.format(dataset=d, method=m, seed=s)
                      for d, m, s in SETTINGS.jobs()],
        manifests=train_manifests(),
        # The calibration record is optional (calibrate runs by hand), but the audit checks it when present:
        # declared then, so a run of calibrate finishes before the audit reads it and a new record re-audits.
        calibration=lambda wildcards: [p for p in rules.calibrate.output if Path(p).exists()],
    output:
        json="results/audit/report.json",
        md="results/audit/report.md",
    params:
        settings=S.param(S.audit_slice(SETTINGS)),
        configfiles=S.Untracked([str(f) for f in workflow.configfiles]),
    log:
        "logs/audit/report.log",
    benchmark:
        "results/benchmarks/audit/report.tsv"
    script:
        "../scripts/audit.py"


rule audit:
    input:
        report=rules.audit_report.output.json,
    output:
        passed="results/audit/passed",
    log:
        "logs/audit/gate.log",
    script:
        "../scripts/audit.py"
