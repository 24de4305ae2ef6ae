# Helpers shared by the rule files: the settings, resolved once here, and the target lists.
# Every rule passes its job exactly the slice of settings the job reads (`params.settings`, canonical JSON with
# sorted keys): that slice is the job's rerun trigger. `params.display` (how a job reports) is a typed object,
# which Snakemake does not compare, so changing it reruns nothing. Scripts never read `snakemake.config`.
import sys
from pathlib import Path

sys.path.insert(0, str(Path(workflow.basedir) / "src"))

from snakemake.exceptions import WorkflowError

from dswm import settings as S
from dswm.config import ConfigError
from prep.config import DATASETS as DATASET_NAMES


def config_sources():
    """Where each value of `config` came from: config.yaml, each --configfile (as given, relative to the working
    directory when under it), then --config (Snakemake applies them in this order)."""
    from dswm.config import ConfigSources, load_yaml

    def shown(path):
        path = Path(path)
        return str(path.relative_to(Path.cwd())) if path.is_relative_to(Path.cwd()) else str(path)

    layers = [(shown(f), load_yaml(f)) for f in workflow.config_settings.configfiles]
    if workflow.config_settings.config:
        layers.append((ConfigSources.CLI, dict(workflow.config_settings.config)))
    return ConfigSources(layers=tuple(layers))


CONFIG_SOURCES = config_sources()
"""Names the file (or --config) of a key in every config message."""


def with_source(fn, *args):
    """``fn(*args)``; a ConfigError it raises names where its key's value came from (CONFIG_SOURCES)."""
    try:
        return fn(*args)
    except ConfigError as err:
        raise ConfigError(CONFIG_SOURCES.relabel(str(err))) from None


# Bad config stops the run here, before any job: the message names the key, where its value came from and the
# expected form.
try:
    SETTINGS = S.resolve(config, root=Path.cwd(), schema=Path(workflow.basedir) / "workflow" / "schemas" /
                         "config.schema.yaml", sources=CONFIG_SOURCES)
except ConfigError as err:
    raise WorkflowError(str(err)) from None

PROFILE = SETTINGS.profile
DATASETS = list(SETTINGS.run.datasets)
MAIN_DATASET = SETTINGS.tables.main_dataset
"""The dataset of Table III (`results/tables/<main_dataset>_main.*`); one the profile evaluates."""
METHODS = list(SETTINGS.methods)
TRAINED = SETTINGS.trained()
"""The learning methods the `train` rule fits; every other learning method evaluates its source's model."""
TRAINED_PATTERN = "|".join(TRAINED) or "(?!)"
"""The `train` rule's method constraint: a model.pt of a method that shares a training cannot be requested."""
DISPLAY = SETTINGS.display
TRACKING = S.tracking(SETTINGS)
"""``params.tracking`` of every job that logs to MLflow: the ``mlflow`` section, Untracked. Where and how a run is
logged (server or store, batch size, HTTP retries) reruns no job; the experiment's name is in the jobs' slices."""
INTENSITY = S.intensity_inputs(SETTINGS)
"""`{"intensity": <the calibrate rule's record>}` when scenario.demand_intensity is `calibrate`, else `{}`: an input
of every job that reads u (select, train, evaluate, audit_report), which takes u from it. A new record reruns
them (the record is an input; their settings slices hold `calibrate`, not the number)."""


def _alternatives(names):
    """A wildcard constraint matching exactly ``names`` (none: nothing)."""
    import re

    return "|".join(re.escape(n) for n in names) or "(?!)"


KNOWN_DATASETS = [name for name in config["datasets"] if name in DATASET_NAMES]
"""Every dataset the config's `datasets:` section holds (its keys but `common`, names prep.config.DATASETS knows;
the schema requires each): the values of the `dataset` wildcard. A profile runs some of them."""


wildcard_constraints:
    dataset=_alternatives(KNOWN_DATASETS),
    method=r"[a-z][a-z0-9_]*",
    seed=r"\d+",


def job_resources(rule, method=None):
    """``resources`` of ``rule``'s jobs for a cluster scheduler (config.yaml ``resources``, profiles/slurm): mem_mb
    and runtime (minutes); for a job that runs torch also ``gpu`` (1 when its device is cuda) and ``slurm_extra``
    (``resources.gpu_slurm_extra`` on a GPU). ``method`` is the method whose device the job uses: "{method}" for
    the job's wildcard, a method's name, "" for evaluation.device alone, None for a job without torch work."""
    r = SETTINGS.resources.of(rule)
    out = {"mem_mb": r.mem_mb, "runtime": r.runtime}
    if method is not None:
        name = (lambda wc: wc.method) if method == "{method}" else (lambda wc: method or None)
        out["gpu"] = lambda wc: int(S.needs_gpu(SETTINGS, name(wc)))
        out["slurm_extra"] = lambda wc: SETTINGS.resources.gpu_slurm_extra if S.needs_gpu(SETTINGS, name(wc)) else ""
    return out


def write_obstacles_message(writers, files_only=False):
    """The error of the paths in the way of ``writers`` ({a path the workflow writes: the rules writing it}), one
    line per obstacle (prep.atomic.write_obstacles; with ``files_only``, files in the way alone); "" when none."""
    from prep.atomic import write_obstacles

    lines = []
    for found, (why, dirs) in write_obstacles(writers).items():
        if files_only and found.is_dir():
            continue
        rules_ = sorted({r for d in dirs for path, names in writers.items() if Path(path).parent == d for r in names})
        shown = ", ".join(map(str, dirs[:3])) + (f" and {len(dirs) - 3} more" if len(dirs) > 3 else "")
        fix = "move the file away" if why.startswith("a file") else f"make {found} writable"
        lines.append(f"{found} is {why}: the outputs of {', '.join(rules_)} cannot be written in {shown}; nothing "
                     f"was run ({fix} and run again)")
    return "\n".join(lines)


def check_output_paths():
    """At parse time (end of the Snakefile): no file stands where a rule writes a directory (results/tables a
    file): Snakemake would stop on it with a raw error while it builds any DAG that touches that directory."""
    writers = {}
    for r in workflow.rules:
        for path in [*r.output, *r.log]:
            static = str(path).split("{", 1)[0]
            writers.setdefault(str(Path(static) / "-") if static != str(path) else str(path), set()).add(r.name)
    message = write_obstacles_message(writers, files_only=True)
    if message:
        raise WorkflowError(message)


def check_outputs_writable():
    """As the workflow starts (onstart, before any job): every directory the jobs about to run write their outputs
    and logs into can take a file. Else the run stops here, naming the directory and the rules, rather than when
    the first job that writes there ends (`build_tables` comes after every evaluation)."""
    writers = {}
    for job in workflow.dag.needrun_jobs():
        for path in [*job.output, *job.log]:
            writers.setdefault(str(path), set()).add(job.rule.name)
    message = write_obstacles_message(writers)
    if message:
        raise WorkflowError(message)


def learns(method):
    """True for methods trained by the `train` rule before evaluation."""
    return method in SETTINGS.methods and SETTINGS.methods[method].learns


def trained_model(wildcards):
    """The trained model and manifest an evaluation needs: its training source's (none for methods that do not
    learn). A method whose training is identical to an earlier one's evaluates that method's model."""
    if not learns(wildcards.method):
        return {}
    source = {**dict(wildcards.items()), "method": SETTINGS.methods[wildcards.method].training_source}
    return {
        "model": rules.train.output.model.format(**source),
        "manifest": rules.train.output.manifest.format(**source),
    }


def reused_evaluation(wildcards, outputs=None, seeds=None):
    """The evaluation an evaluate job reuses: the result files of its dataset's first seed, for a method whose result
    the seed does not change (evaluation.reuse_seed_independent; dswm.settings.reused_seed); none otherwise.
    ``outputs``: the rule's output files (default: the evaluate rule's), ``seeds``: the seeds the rule runs (default:
    the profile's of the dataset)."""
    first = S.reused_seed(SETTINGS, wildcards.dataset, wildcards.method, int(wildcards.seed), seeds)
    if first is None:
        return {}
    source = {**dict(wildcards.items()), "seed": first}
    outputs = rules.evaluate.output if outputs is None else outputs
    return {f"reuse_{name}": getattr(outputs, name).format(**source) for name in S.REUSED_FILES}


def start_priority(wildcards):
    """A train or evaluate job's Snakemake priority: resources.start_order's methods first, the first the highest
    (scheduling only)."""
    return SETTINGS.resources.priority(wildcards.method)


def train_manifests():
    """The training manifest of every train job of the selected profile (one per training source and seed)."""
    return [
        rules.train.output.manifest.format(dataset=d, method=m, seed=s)
        for d, m, s in SETTINGS.jobs()
        if m in TRAINED
    ]


def result_files():
    """Every per-day result file of the selected profile."""
    return [rules.evaluate.output.days.format(dataset=d, method=m, seed=s) for d, m, s in SETTINGS.jobs()]


def meta_files():
    """{dataset: meta.json} of every dataset of the selected profile."""
    return {d: rules.prepare.output.meta.format(dataset=d) for d in DATASETS}


def raw_files(dataset):
    """The raw input files of `dataset` (its demo directory, or its published files)."""
    from prep.pipeline import raw_inputs

    return raw_inputs(getattr(SETTINGS.datasets, dataset), dataset)


def reference_meta(dataset):
    """meta.json of the kappa reference dataset, for every other dataset (docs/PROTOCOL.md §4)."""
    from prep.pipeline import reference_input

    return reference_input(SETTINGS.datasets.common, dataset)


CONDITIONAL_RULES = set()
"""Rules a rule file defines only under some settings (e.g. when DSWM is evaluated): a name `resources.rules` may
give even when the current settings leave the rule out (Snakefile)."""


# ---- figures (workflow/rules/figures.smk and the rule files of the extra runs) ----
FIGURES_SETTINGS = SETTINGS.figures
"""config.yaml ``figures`` merged with ``figures.budgets.<profile>``."""
FIGURE_DIR = "results/figures"
FIGURE_TARGETS = []
"""Every file the `figures` target asks for; each figure rule file appends its figures' PNG, PDF and CSV."""


def figure_outputs(name, category, subcategory=None, figures=True):
    """The outputs of figure ``name``: PNG (in the Snakemake report, captioned by workflow/report/<name>.rst),
    PDF and CSV under results/figures/; the three are added to the `figures` target unless ``figures`` is False
    (a figure with a target of its own, e.g. `room_fill`)."""
    files = {ext: f"{FIGURE_DIR}/{name}.{ext}" for ext in ("png", "pdf", "csv")}
    if figures:
        FIGURE_TARGETS.extend(files.values())
    labels = {"figure": name}
    return {
        "png": report(files["png"], caption=f"../report/{name}.rst", category=category, subcategory=subcategory,
                      labels=labels),
        "pdf": files["pdf"],
        "csv": report(files["csv"], caption=f"../report/{name}.rst", category=category,
                      subcategory=subcategory, labels={"figure": name, "file": "data (CSV)"}),
    }


def figure_attach(stages, datasets=None, methods=None):
    """``params.attach`` of a figure rule: the FINISHED MLflow runs its PNG and PDF are logged beside, those of
    ``stages`` restricted to ``datasets`` and ``methods`` (None: any) of this profile
    (dswm.pipeline.tracking.attach_figure_outputs). Untracked: which runs show a figure changes no figure."""
    return S.Untracked({"mlflow": TRACKING.value, "profile": PROFILE, "stages": list(stages),
                        "datasets": None if datasets is None else list(datasets),
                        "methods": None if methods is None else list(methods)})


# The extra runs (extra.smk): EXTRA_VARIANTS, FIG_DATASET and the extra_* rules are defined there.
def extra_model(wildcards):
    """The model an extra evaluation loads: its training source's, from the main `train` rule when the variant
    does not change the source's train slice, else from `extra_train` (none for a method that does not learn)."""
    if not learns(wildcards.method):
        return {}
    variant = EXTRA_VARIANTS[wildcards.variant]
    source = {**dict(wildcards.items()), "method": SETTINGS.methods[wildcards.method].training_source}
    producer = rules.extra_train if S.variant_retrains(SETTINGS, wildcards.method, variant) else rules.train
    return {"model": producer.output.model.format(**source), "manifest": producer.output.manifest.format(**source)}


def extra_days(kinds):
    """The days.parquet of every extra run of the variant kinds ``kinds`` ("do", "K", "u")."""
    return [rules.extra_evaluate.output.days.format(dataset=FIG_DATASET, variant=v, method=m, seed=s)
            for v, m, s in S.extra_jobs(SETTINGS) if EXTRA_VARIANTS[v].kind in kinds]


def main_days(methods, seeds):
    """The main evaluations' days.parquet of ``methods`` and ``seeds`` on `figures.dataset`."""
    return [rules.evaluate.output.days.format(dataset=FIG_DATASET, method=m, seed=s) for m in methods for s in seeds]


# The extra audit (extra.smk: audit_extra; audit.smk: audit): _EXTRA_AUDITED is defined in extra.smk.
def extra_audit_runs():
    """[dataset, variant, method, seed, whether the variant retrains the method] of every extra run the figures draw,
    as the extra audit takes them (audits.extra.extra_runs: its settings slice has no figures section)."""
    return [[d, v, m, s, learns(m) and S.variant_retrains(SETTINGS, m, EXTRA_VARIANTS[v])]
            for d, v, m, s in dict.fromkeys(_EXTRA_AUDITED)]


def extra_audit_files():
    """Every file the extra audit reads that a rule writes: the result files and content record of each extra run
    the figures draw, and the model and training manifest each of its learning methods loaded (extra_model)."""
    out = []
    for d, v, m, s in dict.fromkeys(_EXTRA_AUDITED):
        keys = {"dataset": d, "variant": v, "method": m, "seed": s}
        out += [pattern.format(**keys) for pattern in rules.extra_evaluate.output]
        if learns(m):
            source = {**keys, "method": SETTINGS.methods[m].training_source}
            producer = rules.extra_train if S.variant_retrains(SETTINGS, m, EXTRA_VARIANTS[v]) else rules.train
            out += [producer.output.model.format(**source), producer.output.manifest.format(**source)]
    return list(dict.fromkeys(out))


# The foresight and headroom figures (headroom.smk): their runs are extra_evaluate's, on datasets of their own.
def extra_files_of(jobs):
    """The days.parquet of the extra runs ``jobs``: (dataset, variant, method, seed) tuples
    (dswm.settings.foresight_jobs, headroom_jobs)."""
    return [rules.extra_evaluate.output.days.format(dataset=d, variant=v, method=m, seed=s) for d, v, m, s in jobs]


def figure_main_files(datasets, methods):
    """The main evaluations' days.parquet of ``methods`` on ``datasets`` that the profile evaluates there, for the
    seeds of `figures.seeds` it runs there (dswm.settings.figure_seeds)."""
    return [rules.evaluate.output.days.format(dataset=d, method=m, seed=s) for d in datasets
            for m in dict.fromkeys(methods) if m in SETTINGS.methods_on(d) for s in S.figure_seeds(SETTINGS, d)]


def plain_cells(cells):
    """The foresight grid's cells (dswm.settings.foresight_cells) as params: each variant by its name."""
    return [{**c, "variant": None if c["variant"] is None else c["variant"].name} for c in cells]


# Figure room_fill (room_fill.smk): ROOM_FILL_ARMS_ON, ROOM_FILL_VARIANT and its rules are defined there.
def room_fill_model(wildcards, method=None):
    """The world model of an arm (none for a method that does not learn): its training source's, trained in the
    regime (extra_train) when the regime changes the train slice, else the main train rule's."""
    method = method or ROOM_FILL_ARMS_ON[wildcards.arm]
    if not learns(method):
        return {}
    source = SETTINGS.methods[method].training_source
    keys = {"dataset": wildcards.dataset, "seed": wildcards.seed, "method": source}
    if ROOM_FILL_VARIANT is not None and S.variant_retrains(SETTINGS, method, ROOM_FILL_VARIANT):
        producer, keys = rules.extra_train, {**keys, "variant": ROOM_FILL_VARIANT.name}
    else:
        producer = rules.train
    return {"model": producer.output.model.format(**keys), "manifest": producer.output.manifest.format(**keys)}


# The learning audit (learning.smk: audit_learning, learning; audit.smk: audit): LEARNERS and the learning rules
# are defined in learning.smk.
def learning_audit_files():
    """Every file the learning audit reads that a rule writes: the runs' manifests and snapshots, and every curve."""
    return (learning_files(rules.learning_train.output.manifest, LEARNERS)
            + learning_files(rules.learning_train.output.snapshots, LEARNERS)
            + learning_files(rules.learning_score.output.curve, LEARNERS + LEARNING_REFERENCES))


# The sample-efficiency probe (probes.smk): PROBE_JOBS and the probe rule are defined there.
def probe_files():
    """The probe file of every probe job of the profile (audit.smk reads those that exist)."""
    return [rules.probe.output.probe.format(dataset=d, method=m, seed=s) for d, m, s in PROBE_JOBS]


# DSWM's own figures (wm.smk): WM_METHOD, WM_DIR and the wm_quality rule are defined there.
def dswm_runs_on(dataset):
    """True when the profile trains and evaluates WM_METHOD on ``dataset``."""
    return dataset in DATASETS and WM_METHOD in TRAINED and WM_METHOD in SETTINGS.methods_on(dataset)


def wm_model(wildcards):
    """The model, training manifest and main days.parquet of WM_METHOD for the quality job's (dataset, seed)."""
    keys = {"dataset": wildcards.dataset, "method": WM_METHOD, "seed": wildcards.seed}
    return {"model": rules.train.output.model.format(**keys), "manifest": rules.train.output.manifest.format(**keys),
            "main_days": rules.evaluate.output.days.format(**keys)}


def wm_files(dataset, name):
    """The quality job's ``name`` file of every main seed of ``dataset``."""
    return [f"{WM_DIR}/{name}".format(dataset=dataset, seed=s) for s in SETTINGS.seeds(dataset)]


def main_run(dataset, method, seed, output="days"):
    """A main evaluation's output file."""
    return getattr(rules.evaluate.output, output).format(dataset=dataset, method=method, seed=seed)


# The learning curves (learning.smk): LEARNING, LEARNERS and the learning_* rules are defined there.
def learning_snapshots(wildcards):
    """The snapshots a learning_score job scores: its learner's run's (none for a reference method)."""
    if wildcards.method not in LEARNERS:
        return {}
    return {"snapshots": rules.learning_train.output.snapshots.format(**dict(wildcards.items()))}


def learning_priority(wildcards):
    """A learning job's Snakemake priority: learning.start_order's learners first, the longest run first
    (dswm.settings.learning_priority)."""
    return S.learning_priority(LEARNING, LEARNERS, wildcards.method)


def learning_files(output, methods):
    """``output`` (a learning rule's output pattern) of every method of ``methods`` at learning.dataset and
    learning.seed."""
    return [output.format(dataset=LEARNING.dataset, method=m, seed=LEARNING.seed) for m in methods]
