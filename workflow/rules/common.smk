# Helpers shared by the rule files (config validation and resolution, wildcard constraints, target lists).
import sys
from pathlib import Path

sys.path.insert(0, str(Path(workflow.basedir) / "src"))

from snakemake.exceptions import WorkflowError
from snakemake.utils import validate

from dswm import controllers, runconfig
from dswm.config import ConfigError, Scenario

SCHEMA = Path(workflow.basedir) / "workflow" / "schemas" / "config.schema.yaml"


# Bad config stops the run here, before any job: the message names the key and the expected form.
try:
    runconfig.validate_config(config, runconfig.load_schema(SCHEMA))
    validate(config, schema=str(SCHEMA), set_default=False)
    RUN = runconfig.resolve(config)
    Scenario.from_dict(RUN["scenario"])   # the constants' cross-key checks (e.g. obs_window < slots_per_day)
    runconfig.check_profile_datasets(RUN)
    METHOD_CLASSES = controllers.check_methods(RUN)
    TRAIN_SOURCE = controllers.training_sources(RUN)
    runconfig.check_raw_files(RUN, Path.cwd())
except ConfigError as err:
    raise WorkflowError(str(err)) from None

PROFILE = RUN["profile"]
DATASETS = list(RUN["run"]["datasets"])
MAIN_DATASET = RUN["tables"]["main_dataset"]
"""The dataset of Table III (`results/tables/<main_dataset>_main.*`); one the profile evaluates."""
if MAIN_DATASET not in DATASETS:
    raise WorkflowError(f"config.yaml: key 'tables.main_dataset' is {MAIN_DATASET!r}, which profile {PROFILE!r} "
                        f"does not run (profiles.{PROFILE}.datasets: {', '.join(DATASETS)})")
METHODS = list(RUN["methods"]["run"])
TRAINED = [m for m in METHODS if TRAIN_SOURCE.get(m) == m]
"""The learning methods the `train` rule fits; every other learning method evaluates its source's model."""
TRAINED_PATTERN = "|".join(TRAINED) or "(?!)"
"""The `train` rule's method constraint: a model.pt of a method that shares a training cannot be requested."""


wildcard_constraints:
    dataset="milan|shanghai|yjmob",
    method=r"[a-z][a-z0-9_]*",
    seed=r"\d+",


def learns(method):
    """True for methods trained by the `train` rule before evaluation."""
    return method in METHOD_CLASSES and METHOD_CLASSES[method].learns


def trained_model(wildcards):
    """The trained model and manifest an evaluation needs: its training source's (none for methods that do not
    learn). A method whose training is identical to an earlier one's evaluates that method's model."""
    if not learns(wildcards.method):
        return {}
    source = {**dict(wildcards.items()), "method": TRAIN_SOURCE[wildcards.method]}
    return {
        "model": rules.train.output.model.format(**source),
        "manifest": rules.train.output.manifest.format(**source),
    }


def train_manifests():
    """The training manifest of every train job of the selected profile (one per training source and seed)."""
    return [
        rules.train.output.manifest.format(dataset=d, method=m, seed=s)
        for d, m, s in runconfig.jobs(RUN)
        if m in TRAINED
    ]


def result_files():
    """Every per-day result file of the selected profile."""
    return [
        rules.evaluate.output.days.format(dataset=d, method=m, seed=s)
        for d, m, s in runconfig.jobs(RUN)
    ]


def meta_files():
    """{dataset: meta.json} of every dataset of the selected profile."""
    return {d: rules.prepare.output.meta.format(dataset=d) for d in DATASETS}


def train_params(wildcards):
    """What a training job depends on besides its input files: its training identity, not planner settings."""
    return controllers.training_rerun_params(RUN, wildcards.method)


def job_params(wildcards):
    """What an evaluation job depends on besides its input files (a change reruns it)."""
    return {
        "profile": PROFILE,
        "eval_days": RUN["run"]["eval_days"],
        "scenario": RUN["scenario"],
        "evaluation": RUN["evaluation"],
        "method": {k: v for k, v in RUN["methods"].items() if k == wildcards.method},
        "user": RUN["methods"]["user"].get(wildcards.method, {}),
        "dswm": RUN.get("dswm", {}) if learns(wildcards.method) else {},
    }
