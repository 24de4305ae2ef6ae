# Figure room_fill: DSWM+ where the room is. In the regime of `figures.room_fill` (a cell of the headroom map: its
# dataset, D_max and u factor), Greedy and Perfect forecast (the room), Algorithm 1, DSWM+, its persistence probe
# and the candidate (DSWM+ with anchoring per imagined step rho_k and a gamma, both chosen on TRAINING days by
# room_fill_fit) on every test day of `figures.room_fill.eval_days`, with the world model trained in the regime
# (extra.smk's extra_train when the regime changes u). Outputs under results/extra/<dataset>/room_fill/: never a
# table's source.
CONDITIONAL_RULES.update({"room_fill_fit", "room_fill_evaluate", "figure_room_fill"})
"""Defined only where the profile runs the regime's dataset with DSWM+; `resources.rules` may name them."""
_RF = FIGURES_SETTINGS.room_fill
ROOM_FILL_ARMS_ON = S.room_fill_arms(SETTINGS)
"""{arm: method} of figure room_fill that the profile evaluates (dswm.settings.room_fill_arms)."""
ROOM_FILL_VARIANT = S.room_fill_variant(SETTINGS)
"""The headroom map's variant of the regime (None: the scenario's own cell)."""
_RF_NAME = "own" if ROOM_FILL_VARIANT is None else ROOM_FILL_VARIANT.name
_RF_TAG = f"fill{_RF_NAME}"
"""The runs' ``variant`` tag and column: their MLflow job keys stay apart from the headroom map's runs."""
RF_DIR = "results/extra/{dataset}/room_fill/{arm}/seed{seed}"


if ROOM_FILL_ARMS_ON:

    rule room_fill_fit:
        input:
            unpack(lambda wc: room_fill_model(wc, "dswm_plus")),
            tensor=rules.prepare.output.tensor,
            meta=rules.prepare.output.meta,
            mlflow=rules.mlflow_init.output.marker,
            **INTENSITY,  # the calibrate rule's record when scenario.demand_intensity is `calibrate`
        output:
            fit="results/extra/{dataset}/room_fill/fit/seed{seed}.json",
        params:
            settings=S.param(S.room_fill_slice(SETTINGS, S.ROOM_FILL_CANDIDATE)),
            tracking=TRACKING,
            display=S.Untracked(DISPLAY),
            variant=_RF_TAG,
        log:
            "logs/room_fill_fit/{dataset}/seed{seed}.log",
        benchmark:
            "results/benchmarks/room_fill_fit/{dataset}/seed{seed}.tsv"
        wildcard_constraints:
            dataset=_RF.dataset,
        threads: 1
        resources:
            **job_resources("room_fill_fit", method="dswm_plus"),
        script:
            "../scripts/room_fill_fit.py"

    rule room_fill_evaluate:
        input:
            unpack(room_fill_model),
            fit=lambda wc: ([rules.room_fill_fit.output.fit.format(dataset=wc.dataset, seed=wc.seed)]
                            if wc.arm == S.ROOM_FILL_CANDIDATE else []),
            tensor=rules.prepare.output.tensor,
            meta=rules.prepare.output.meta,
            mlflow=rules.mlflow_init.output.marker,
            **INTENSITY,  # the calibrate rule's record when scenario.demand_intensity is `calibrate`
        output:
            days=RF_DIR + "/days.parquet",
            trajectory=RF_DIR + "/trajectory.npz",
            record=RF_DIR + "/eval_manifest.json",  # SHA-256 and size of the two files above, written last
        params:
            settings=lambda wc: S.param(S.room_fill_slice(SETTINGS, wc.arm)),
            tracking=TRACKING,
            display=S.Untracked(DISPLAY),
            method=lambda wc: ROOM_FILL_ARMS_ON[wc.arm],
            variant=lambda wc: _RF_TAG + ("rhok" if wc.arm == S.ROOM_FILL_CANDIDATE else ""),
        log:
            "logs/room_fill_evaluate/{dataset}/{arm}/seed{seed}.log",
        benchmark:
            "results/benchmarks/room_fill_evaluate/{dataset}/{arm}/seed{seed}.tsv"
        wildcard_constraints:
            dataset=_RF.dataset,
            arm=_alternatives(ROOM_FILL_ARMS_ON),
        threads: 1
        resources:
            **job_resources("room_fill_evaluate", method="dswm_plus"),  # every arm plans on DSWM+'s device
        script:
            "../scripts/room_fill_evaluate.py"

    rule figure_room_fill:
        input:
            runs=[rules.room_fill_evaluate.output.days.format(dataset=d, arm=a, seed=s)
                  for d, a, s in S.room_fill_jobs(SETTINGS)],
            fits=[rules.room_fill_fit.output.fit.format(dataset=_RF.dataset, seed=s)
                  for s in S.figure_seeds(SETTINGS, _RF.dataset)],
            mlflow=rules.mlflow_init.output.marker,  # the figure is logged beside its runs
        output:
            **figure_outputs("room_fill", "Where foresight pays", figures=False),  # its own target, below
        params:
            attach=figure_attach(["extra"], [_RF.dataset], dict.fromkeys(ROOM_FILL_ARMS_ON.values())),
            profile=PROFILE,
            arms=list(ROOM_FILL_ARMS_ON),
            labels={a: ("DSWM+ rho_k (candidate)" if a == S.ROOM_FILL_CANDIDATE
                        else SETTINGS.methods[m].label) for a, m in ROOM_FILL_ARMS_ON.items()},
            regime={"dataset": _RF.dataset, "d_max_m": float(_RF.d_max_m),
                    "intensity_scale": float(_RF.intensity_scale)},
            split_labels={"id": SETTINGS.tables.split_labels.id, "ood": SETTINGS.tables.split_labels.ood},
        log:
            "logs/figures/room_fill.log",
        benchmark:
            "results/benchmarks/figures/room_fill.tsv"
        threads: 1
        resources:
            **job_resources("figure_room_fill"),
        script:
            "../scripts/figure_room_fill.py"


    # The target: `snakemake --cores 2 room_fill`, after `tables` (not part of `tables` or `figures`: its training in
    # the regime, fit and six arms cost ~4.5 CPU-minutes on the demo, which `figures` has no room for within 20 min).
    rule room_fill:
        input:
            rules.figure_room_fill.output,
