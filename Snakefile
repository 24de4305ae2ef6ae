# DSWM pipeline: raw demand data -> demand tensors -> trained and evaluated controllers -> tables.
# Main job: `snakemake --cores 2 tables` (the default target); profile: `--config profile=smoke|demo|paper`.
from snakemake.utils import min_version

min_version("9.0")


configfile: "config.yaml"


# The Snakemake report (`snakemake --cores 2 --report results/report.html figures`, once `figures` has run): every
# table and figure with its caption (workflow/report/*.rst), grouped in categories.
report: "workflow/report/workflow.rst"


include: "workflow/rules/common.smk"
include: "workflow/rules/prep.smk"
include: "workflow/rules/mlflow.smk"
include: "workflow/rules/calibrate.smk"
include: "workflow/rules/select.smk"
include: "workflow/rules/train.smk"
include: "workflow/rules/evaluate.smk"
include: "workflow/rules/audit.smk"
include: "workflow/rules/tables.smk"
include: "workflow/rules/extra.smk"
include: "workflow/rules/probes.smk"
include: "workflow/rules/wm.smk"
include: "workflow/rules/headroom.smk"
include: "workflow/rules/room_fill.smk"
include: "workflow/rules/learning.smk"
include: "workflow/rules/figures.smk"


# `snakemake --cores 2` with no target runs `tables`. Its `default_target: True` sits in an included file, and
# Snakemake restores the default target when an include returns, so it is set here in the main Snakefile.
workflow.default_target = "tables"

# Rules that only read result files and write small tables and figures run on the submitting machine when a
# cluster executor sends the other jobs away (profiles/slurm); a local run is unchanged.
workflow.localrules("tables", "build_tables", "figures", *[r.name for r in workflow.rules if r.name.startswith("figure_")])


# No file stands where a rule writes (a file named results/tables): named here, before any DAG is built.
check_output_paths()


# A rule that `resources.rules` names must exist: a misspelled rule would silently keep the default resources.
_unknown = sorted(set(SETTINGS.resources.rules) - {r.name for r in workflow.rules} - CONDITIONAL_RULES)
if _unknown:
    raise WorkflowError(CONFIG_SOURCES.relabel(
        f"config.yaml: key 'resources.rules' names {', '.join(map(repr, _unknown))}, which is no rule of this "
        f"workflow (rules: {', '.join(sorted(r.name for r in workflow.rules))})"))
# A method that `resources.start_order` names must be one (built-in or under methods.user), run or not.
from dswm.methods.registry import BUILTIN

_unknown = sorted(set(SETTINGS.resources.start_order) - set(BUILTIN) - set(config["methods"].get("user") or {}))
if _unknown:
    raise WorkflowError(CONFIG_SOURCES.relabel(
        f"config.yaml: key 'resources.start_order' names {', '.join(map(repr, _unknown))}, which is no method "
        f"(expected built-in ones: {', '.join(sorted(BUILTIN))}, or methods under 'methods.user')"))


# The parsed workflow and the libraries its settings import live as long as this process: the cyclic garbage
# collector leaves them alone from here on (dswm.pipeline.heap), which ends a dry run ~1 s sooner and so each job's
# own Snakemake on a cluster.
from dswm.pipeline.heap import freeze_heap

freeze_heap()
