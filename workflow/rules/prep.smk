# Data preparation (docs/PROTOCOL.md §4): demo raw files, demand tensors, exploratory statistics.


rule demo_raw:
    output:
        raw=directory("results/raw/{dataset}/demo"),
    params:
        settings=lambda wc: S.param(S.prep_slice(SETTINGS, wc.dataset)),
    log:
        "logs/prep/demo_raw_{dataset}.log",
    benchmark:
        "results/benchmarks/prep/demo_raw_{dataset}.tsv"
    threads: 1
    resources:
        **job_resources("demo_raw"),
    script:
        "../scripts/demo_raw.py"


rule prepare:
    input:
        raw=lambda wc: raw_files(wc.dataset),
        reference=lambda wc: reference_meta(wc.dataset),
    output:
        tensor="results/data/{dataset}/demand.parquet",
        meta="results/data/{dataset}/meta.json",
    params:
        settings=lambda wc: S.param(S.prep_slice(SETTINGS, wc.dataset)),
    log:
        "logs/prep/prepare_{dataset}.log",
    benchmark:
        "results/benchmarks/prep/prepare_{dataset}.tsv"
    threads: 1
    resources:
        **job_resources("prepare"),
    script:
        "../scripts/prep_prepare.py"


rule eda:
    input:
        tensor=rules.prepare.output.tensor,
        meta=rules.prepare.output.meta,
    output:
        stats="results/eda/{dataset}/eda.json",
        figure="results/eda/{dataset}/eda.png",
    params:
        settings=S.param(S.eda_slice(SETTINGS)),
    log:
        "logs/prep/eda_{dataset}.log",
    threads: 1
    resources:
        **job_resources("eda"),
    script:
        "../scripts/eda.py"
