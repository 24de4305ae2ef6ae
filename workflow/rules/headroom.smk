# The two figures of where foresight pays. `foresight`: demand source x planner on every dataset of `figures.foresight` (Algorithm 1's
# planner and DSWM+'s, each on persistence, the world model anchored by rho and the true maps), beside the world
# model's demand RMSE against persistence's (the wm_quality replay of each dataset). `headroom`: Greedy, Perfect
# forecast and Ceiling over D_max x u on the datasets of `figures.headroom`. A cell that is a method's main
# evaluation is that file cut to the figure's days; the others are extra runs of extra.smk's rules (the foresight
# grid's with the same trained model: no training). Outputs under results/extra/: never a table's source.
CONDITIONAL_RULES.update({"figure_foresight", "figure_headroom"})
"""Defined only where the profile runs a dataset of their grid; `resources.rules` may name them."""
_FORESIGHT = {d: S.foresight_cells(SETTINGS, d) for d in FIGURES_SETTINGS.foresight.datasets if d in DATASETS}
_HEADROOM = [d for d in FIGURES_SETTINGS.headroom.datasets if d in DATASETS]
_HR = FIGURES_SETTINGS.headroom


if _FORESIGHT:

    rule figure_foresight:
        input:
            main=figure_main_files(_FORESIGHT, ["greedy", "perfect", *S.SOURCE_METHODS.values()]),
            runs=extra_files_of(S.foresight_jobs(SETTINGS)),
            rmse=[p for d in _FORESIGHT if WM_METHOD in TRAINED and dswm_runs_on(d) for p in wm_files(d, "rmse.parquet")],
            mlflow=rules.mlflow_init.output.marker,  # the figure is logged beside its runs
        output:
            **figure_outputs("foresight", "Where foresight pays"),
        params:
            attach=figure_attach(["evaluate", "extra", "wm"], list(_FORESIGHT),
                                 ["greedy", "perfect", *dict.fromkeys(S.SOURCE_METHODS.values())]),
            profile=PROFILE,
            cells={d: plain_cells(c) for d, c in _FORESIGHT.items()},
            seeds={d: S.figure_seeds(SETTINGS, d) for d in _FORESIGHT},
            eval_days=to_plain(FIGURES_SETTINGS.foresight.eval_days),
        log:
            "logs/figures/foresight.log",
        benchmark:
            "results/benchmarks/figures/foresight.tsv"
        threads: 1
        resources:
            **job_resources("figure_foresight"),
        script:
            "../scripts/figure_foresight.py"


if _HEADROOM:

    rule figure_headroom:
        input:
            main=figure_main_files(_HEADROOM, S.HEADROOM_METHODS),
            runs=extra_files_of(S.headroom_jobs(SETTINGS)),
            mlflow=rules.mlflow_init.output.marker,  # the figure is logged beside its runs
        output:
            **figure_outputs("headroom", "Where foresight pays"),
        params:
            attach=figure_attach(["evaluate", "extra"], _HEADROOM, list(S.HEADROOM_METHODS)),
            profile=PROFILE,
            datasets=_HEADROOM,
            d_max_m=[float(d) for d in _HR.d_max_m],
            intensity_scales=[float(f) for f in _HR.intensity_scales],
            own_d_max=float(SETTINGS.scenario.d_max_m),
            min_room=float(_HR.min_room),
            names=[[float(d), float(f), getattr(S.headroom_variant(SETTINGS, d, f), "name", None)]
                   for d in [*_HR.d_max_m, SETTINGS.scenario.d_max_m] for f in _HR.intensity_scales],
            seeds={d: S.figure_seeds(SETTINGS, d) for d in _HEADROOM},
            eval_days=to_plain(_HR.eval_days),
        log:
            "logs/figures/headroom.log",
        benchmark:
            "results/benchmarks/figures/headroom.tsv"
        threads: 1
        resources:
            **job_resources("figure_headroom"),
        script:
            "../scripts/figure_headroom.py"
