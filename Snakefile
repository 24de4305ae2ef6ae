# DSWM pipeline: raw demand data -> demand tensors -> trained and evaluated controllers -> tables.
# Main job: `snakemake --cores 2 tables` (the default target); profile: `--config profile=smoke|demo|paper`.
from snakemake.utils import min_version

min_version("9.0")


configfile: "config.yaml"


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
include: "workflow/rules/figures.smk"
