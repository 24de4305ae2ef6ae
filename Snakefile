# DSWM pipeline: raw demand data -> demand tensors -> trained and evaluated controllers -> tables.
from snakemake.utils import min_version

min_version("9.0")


configfile: "config.yaml"


include: "workflow/rules/common.smk"
include: "workflow/rules/prep.smk"
