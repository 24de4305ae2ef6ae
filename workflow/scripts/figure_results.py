"""Figures of the evaluation results and the data (main, ood, cross_dataset, eda): one rule each, this script.

The rule's name says which: figure_main, figure_ood, figure_cross_dataset or figure_eda."""
import sys

sys.stderr = open(snakemake.log[0], "w", buffering=1)  # noqa: F821 (injected by Snakemake)

from dswm.figures.results import figure_job  # noqa: E402
from dswm.settings import read_param  # noqa: E402

smk = snakemake  # noqa: F821
figure_job(smk.rule.removeprefix("figure_"), job=read_param(smk.params.settings),
           mlflow_cfg=smk.params.tracking.value, inputs=smk.input,
           out={k: smk.output[k] for k in ("png", "pdf", "csv")})
