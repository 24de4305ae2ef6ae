# DSWM's own figures: the training diagnostics (paper Fig. 11, from the train jobs' loss histories), the world-model
# quality on the test period (paper Fig. 12) and the qualitative figures (paper Figs. 14-16, Section V-K).
# The quality job replays each DSWM model of `figures.dataset` (every main seed of the profile, so panel (b) has
# one point per seed and day) on the days of its main evaluation cut to `figures.eval_days`, and measures its
# world model along the executed actions (dswm.methods.dswm.quality). Outputs under results/extra/: never a
# table's source. Figures of a dataset or method the profile does not run are left out.
from pathlib import Path

from dswm.config import to_plain

WM_METHOD = "dswm"
"""The method whose world model the figures measure (the paper's DSWM)."""
WM_DATASET = FIGURES_SETTINGS.dataset
WM_DIR = "results/extra/{dataset}/wm_quality/seed{seed}"
MILAN_ASSETS = Path(workflow.basedir) / "src" / "prep" / "assets" / "milan"
CONDITIONAL_RULES.update({"wm_quality", "figure_wm_quality", "figure_training", "figure_qualitative_trajectories",
                          *(f"figure_qualitative_{d}" for d in KNOWN_DATASETS)})
"""The rules below are defined only when the profile runs what they draw; `resources.rules` may name them all."""


if WM_METHOD in TRAINED:

    rule wm_quality:
        input:
            unpack(wm_model),
            tensor=rules.prepare.output.tensor,
            meta=rules.prepare.output.meta,
            mlflow=rules.mlflow_init.output.marker,
            **INTENSITY,  # the calibrate rule's record when scenario.demand_intensity is `calibrate`
        output:
            rmse=f"{WM_DIR}/rmse.parquet",
            returns=f"{WM_DIR}/returns.parquet",
            maps=f"{WM_DIR}/maps.npz",
            record=f"{WM_DIR}/record.json",  # written last: SHA-256 and size of the three above
        params:
            settings=S.param({**S.evaluate_slice(SETTINGS, WM_METHOD),
                              "wm_quality": to_plain(FIGURES_SETTINGS.wm_quality),
                              "replay_days": to_plain(FIGURES_SETTINGS.eval_days)}),
            tracking=TRACKING,
            display=S.Untracked(DISPLAY),
        log:
            "logs/wm/{dataset}/seed{seed}.log",
        benchmark:
            "results/benchmarks/wm_quality/{dataset}/seed{seed}.tsv"
        threads: 1
        resources:
            **job_resources("wm_quality", method=WM_METHOD),
        script:
            "../scripts/wm_quality.py"


if dswm_runs_on(WM_DATASET):

    rule figure_wm_quality:
        input:
            rmse=wm_files(WM_DATASET, "rmse.parquet"),
            returns=wm_files(WM_DATASET, "returns.parquet"),
            meta=rules.prepare.output.meta.format(dataset=WM_DATASET),
            mlflow=rules.mlflow_init.output.marker,  # the figure is logged beside its runs
        output:
            **figure_outputs("wm_quality", "World model"),
        params:
            attach=figure_attach(["wm", "evaluate"], [WM_DATASET], [WM_METHOD]),
            profile=PROFILE,
        log:
            "logs/figures/wm_quality.log",
        benchmark:
            "results/benchmarks/figures/wm_quality.tsv"
        threads: 1
        resources:
            **job_resources("figure_wm_quality"),
        script:
            "../scripts/figure_wm_quality.py"


_TRAINING_DATASETS = [d for d in DATASETS if dswm_runs_on(d)]
if _TRAINING_DATASETS:

    rule figure_training:
        input:
            histories=[rules.train.output.history.format(dataset=d, method=WM_METHOD, seed=s)
                       for d in _TRAINING_DATASETS for s in SETTINGS.seeds(d)],
            metas=[rules.prepare.output.meta.format(dataset=d) for d in _TRAINING_DATASETS],
            mlflow=rules.mlflow_init.output.marker,  # the figure is logged beside its runs
        output:
            **figure_outputs("training", "Training"),
        params:
            attach=figure_attach(["train"], _TRAINING_DATASETS, [WM_METHOD]),
            profile=PROFILE,
            datasets=_TRAINING_DATASETS,
        log:
            "logs/figures/training.log",
        benchmark:
            "results/benchmarks/figures/training.tsv"
        threads: 1
        resources:
            **job_resources("figure_training"),
        script:
            "../scripts/figure_training.py"


if dswm_runs_on("milan"):

    rule figure_qualitative_milan:
        input:
            maps=wm_files("milan", "maps.npz")[0],  # the first main seed's first replayed day
            meta=rules.prepare.output.meta.format(dataset="milan"),
            grid=str(MILAN_ASSETS / "milano-grid.geojson"),
            totals=str(MILAN_ASSETS / "square_totals_2mo.csv"),
            mlflow=rules.mlflow_init.output.marker,  # the figure is logged beside its runs
        output:
            **figure_outputs("qualitative_milan", "Qualitative"),
        params:
            attach=figure_attach(["wm"], ["milan"], [WM_METHOD]),
            profile=PROFILE,
            kind="milan",
        log:
            "logs/figures/qualitative_milan.log",
        benchmark:
            "results/benchmarks/figures/qualitative_milan.tsv"
        threads: 1
        resources:
            **job_resources("figure_qualitative_milan"),
        script:
            "../scripts/figure_qualitative.py"


for _region in ("shanghai", "yjmob"):
    if _region in DATASETS:

        rule:
            name:
                f"figure_qualitative_{_region}"
            input:
                raw=raw_files(_region),
                tensor=rules.prepare.output.tensor.format(dataset=_region),
                meta=rules.prepare.output.meta.format(dataset=_region),
                mlflow=rules.mlflow_init.output.marker,  # the figure is logged beside its runs
            output:
                **figure_outputs(f"qualitative_{_region}", "Qualitative"),
            params:
                attach=figure_attach(["evaluate"], [_region]),
                profile=PROFILE,
                kind=_region,
                settings=S.param(S.prep_slice(SETTINGS, _region)),
            log:
                f"logs/figures/qualitative_{_region}.log",
            benchmark:
                f"results/benchmarks/figures/qualitative_{_region}.tsv"
            threads: 1
            resources:
                **job_resources(f"figure_qualitative_{_region}"),
            script:
                "../scripts/figure_qualitative.py"


_TRAJECTORY_METHODS = FIGURES_SETTINGS.present([WM_METHOD, "greedy"], SETTINGS)
if _TRAJECTORY_METHODS:

    rule figure_qualitative_trajectories:
        input:
            trajectories=[main_run(WM_DATASET, m, SETTINGS.seeds(WM_DATASET)[0], "trajectory")
                          for m in _TRAJECTORY_METHODS],
            tensor=rules.prepare.output.tensor.format(dataset=WM_DATASET),
            meta=rules.prepare.output.meta.format(dataset=WM_DATASET),
            mlflow=rules.mlflow_init.output.marker,  # the figure is logged beside its runs
        output:
            **figure_outputs("qualitative_trajectories", "Qualitative"),
        params:
            attach=figure_attach(["evaluate"], [WM_DATASET], _TRAJECTORY_METHODS),
            profile=PROFILE,
            kind="trajectories",
            methods=_TRAJECTORY_METHODS,
            labels={m: SETTINGS.methods[m].label for m in _TRAJECTORY_METHODS},
        log:
            "logs/figures/qualitative_trajectories.log",
        benchmark:
            "results/benchmarks/figures/qualitative_trajectories.tsv"
        threads: 1
        resources:
            **job_resources("figure_qualitative_trajectories"),
        script:
            "../scripts/figure_qualitative.py"
