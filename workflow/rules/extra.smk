# The extra evaluation runs behind paper Fig. 8 (b) (the do(s) probe) and Fig. 10 (the scaling sweeps), and those
# two figures. Each run is the main evaluation with one change, its `variant`: do<s> (the planner's imagined demand
# x s, `planner.imagine_scale`), K<k> (the fleet size) or u<f> (the demand intensity x f, after calibration); on
# `figures.dataset`, seeds `figures.seeds`, days `figures.eval_days`; sized per profile (config.yaml `figures`).
# The same two rules run the foresight grid's and the headroom map's runs (headroom.smk: rho<r>, alg1, D<m>[u<f>],
# on their own datasets and days, dswm.settings.variant_days).
# A learning method evaluates the main train rule's model when the variant's train slice is the main one's (a do
# variant), else the model `extra_train` fits under the variant. Outputs under results/extra/: never a table's
# source. The reference points (s = 1, the scenario's own K, u x 1) are the main evaluations on the same days.
from dswm.figures.ablation import ABLATION_METHODS

EXTRA_VARIANTS = {v.name: v for v in S.figure_variants(SETTINGS)}
"""{name: dswm.settings.Variant} of every extra run the figures need (those of the foresight grid and the headroom
map, headroom.smk, included)."""
EXTRA_DIR = "results/extra/{dataset}/{variant}/{method}/seed{seed}"
FIG_DATASET = FIGURES_SETTINGS.dataset
_missing_seeds = sorted(set(FIGURES_SETTINGS.seeds) - set(SETTINGS.seeds(FIG_DATASET)))
if _missing_seeds:
    raise WorkflowError(CONFIG_SOURCES.relabel(
        f"config.yaml: key 'figures.seeds' holds {_missing_seeds}, which profile {PROFILE!r} does not run on "
        f"{FIG_DATASET} (profiles.{PROFILE}.seeds.{FIG_DATASET}: {SETTINGS.seeds(FIG_DATASET)}); the extra runs are "
        f"compared with those main evaluations"))

_FIGURE_JOBS = [(_v, _m, _s) for _v, _m, _s in S.extra_jobs(SETTINGS)]
_FIGURE_JOBS += [(_v, _m, _s) for _d, _v, _m, _s in S.foresight_jobs(SETTINGS) + S.headroom_jobs(SETTINGS)]
for _v, _m, _s in _FIGURE_JOBS:  # a do variant of a method without an imagined demand stops here
    try:
        S.variant_evaluate_slice(SETTINGS, _m, EXTRA_VARIANTS[_v])
    except ConfigError as err:
        raise WorkflowError(CONFIG_SOURCES.relabel(str(err))) from None


rule extra_train:
    input:
        tensor=rules.prepare.output.tensor,
        meta=rules.prepare.output.meta,
        mlflow=rules.mlflow_init.output.marker,
        **INTENSITY,  # the calibrate rule's record when scenario.demand_intensity is `calibrate`
    output:
        model=EXTRA_DIR + "/model.pt",
        manifest=EXTRA_DIR + "/train_manifest.json",
    params:
        settings=lambda wc: S.param(S.variant_train_slice(SETTINGS, wc.method, EXTRA_VARIANTS[wc.variant])),
        tracking=TRACKING,
        run_dir=lambda wc: EXTRA_DIR.format(**dict(wc.items())) + "/train",
    log:
        "logs/extra_train/{dataset}/{variant}/{method}/seed{seed}.log",
    benchmark:
        "results/benchmarks/extra_train/{dataset}/{variant}/{method}/seed{seed}.tsv"
    wildcard_constraints:
        variant=_alternatives(EXTRA_VARIANTS),
        method=TRAINED_PATTERN,
    threads: 1
    priority: start_priority  # resources.start_order
    resources:
        **job_resources("extra_train", method="{method}"),
    script:
        "../scripts/extra_train.py"


rule extra_evaluate:
    input:
        unpack(extra_model),
        # the first seed's extra run, for a method the seed does not change (dswm.settings.reused_seed)
        unpack(lambda wc: reused_evaluation(wc, rules.extra_evaluate.output, S.figure_seeds(SETTINGS, wc.dataset))),
        tensor=rules.prepare.output.tensor,
        meta=rules.prepare.output.meta,
        mlflow=rules.mlflow_init.output.marker,
        **INTENSITY,  # the calibrate rule's record when scenario.demand_intensity is `calibrate`
    output:
        days=EXTRA_DIR + "/days.parquet",
        trajectory=EXTRA_DIR + "/trajectory.npz",
        record=EXTRA_DIR + "/eval_manifest.json",  # SHA-256 and size of the two files above, written last
    params:
        settings=lambda wc: S.param(S.variant_evaluate_slice(SETTINGS, wc.method, EXTRA_VARIANTS[wc.variant])),
        tracking=TRACKING,
        display=S.Untracked(DISPLAY),
    log:
        "logs/extra_evaluate/{dataset}/{variant}/{method}/seed{seed}.log",
    benchmark:
        "results/benchmarks/extra_evaluate/{dataset}/{variant}/{method}/seed{seed}.tsv"
    wildcard_constraints:
        variant=_alternatives(EXTRA_VARIANTS),
    threads: 1
    priority: start_priority  # resources.start_order
    resources:
        **job_resources("extra_evaluate", method="{method}"),
    script:
        "../scripts/extra_evaluate.py"


_PROBED = FIGURES_SETTINGS.present(FIGURES_SETTINGS.do_probe.methods, SETTINGS)
_ABLATED = FIGURES_SETTINGS.present(ABLATION_METHODS, SETTINGS)
_SCALED = FIGURES_SETTINGS.present(FIGURES_SETTINGS.scaling.methods, SETTINGS)
_FIG_PARAMS = {
    "profile": PROFILE,
    "seeds": list(FIGURES_SETTINGS.seeds),
    "eval_days": {"id": FIGURES_SETTINGS.eval_days.id, "ood": FIGURES_SETTINGS.eval_days.ood},
    "split_labels": {"id": SETTINGS.tables.split_labels.id, "ood": SETTINGS.tables.split_labels.ood},
}


rule figure_ablation:
    input:
        ablation=main_days(_ABLATED, SETTINGS.seeds(FIG_DATASET)),  # panel (a): every seed of the profile
        reference=main_days(_PROBED, FIGURES_SETTINGS.seeds),  # panel (b), s = 1
        probe=extra_days({"do"}),
        mlflow=rules.mlflow_init.output.marker,  # the figure is logged beside its runs
    output:
        **figure_outputs("ablation", "Ablation and counterfactual"),
    params:
        attach=figure_attach(["evaluate", "extra"], [FIG_DATASET], dict.fromkeys(_ABLATED + _PROBED)),
        **_FIG_PARAMS,
        order=_ABLATED,
        probe_methods=_PROBED,
        labels={m: SETTINGS.methods[m].label for m in dict.fromkeys(_ABLATED + _PROBED)},
    log:
        "logs/figures/ablation.log",
    benchmark:
        "results/benchmarks/figures/ablation.tsv"
    threads: 1
    resources:
        **job_resources("figure_ablation"),
    script:
        "../scripts/figure_ablation.py"


rule figure_scaling:
    input:
        reference=main_days(_SCALED, FIGURES_SETTINGS.seeds),  # the scenario's own K and u x 1
        runs=extra_days({"K", "u"}),
        mlflow=rules.mlflow_init.output.marker,  # the figure is logged beside its runs
    output:
        **figure_outputs("scaling", "Scaling"),
    params:
        attach=figure_attach(["evaluate", "extra"], [FIG_DATASET], _SCALED),
        **_FIG_PARAMS,
        methods=_SCALED,
        labels={m: SETTINGS.methods[m].label for m in _SCALED},
        n_uavs=SETTINGS.scenario.n_uavs,
        fleet_sizes=list(FIGURES_SETTINGS.scaling.fleet_sizes),
        intensity_scales=list(FIGURES_SETTINGS.scaling.intensity_scales),
    log:
        "logs/figures/scaling.log",
    benchmark:
        "results/benchmarks/figures/scaling.tsv"
    threads: 1
    resources:
        **job_resources("figure_scaling"),
    script:
        "../scripts/figure_scaling.py"


_EXTRA_AUDITED = [(FIG_DATASET, _v, _m, _s) for _v, _m, _s in S.extra_jobs(SETTINGS)]
_EXTRA_AUDITED += S.foresight_jobs(SETTINGS) + S.headroom_jobs(SETTINGS)
"""(dataset, variant, method, seed) of every extra run the figures draw: what the extra audit checks
(audits.extra.extra_runs derives the same list from the settings)."""


# The extra part of the leakage audit (audits.runner.SCOPES["extra"]: protocol.extra_runs over the figures' extra
# runs under results/extra/), its own report whatever the verdict; the `figures` target passes only when it passed.
rule audit_extra:
    input:
        extra_audit_files(),
        metas=expand(rules.prepare.output.meta, dataset=DATASETS),
    output:
        json=EXTRA_AUDIT["json"],
        md=report(EXTRA_AUDIT["md"], caption="../report/audit_extra.rst", category="Leakage audit",
                  labels={"report": "extra audit"}),
    params:
        settings=AUDIT_SETTINGS,
        configfiles=S.Untracked([str(f) for f in workflow.configfiles]),
        scope="extra",
        extra_runs=extra_audit_runs(),  # the audit's settings slice has no figures section
    log:
        "logs/audit/extra.log",
    threads: 1
    resources:
        **job_resources("audit_extra"),
    script:
        "../scripts/audit.py"
