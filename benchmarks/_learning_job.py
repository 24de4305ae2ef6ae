"""The set-up of a learning-curve job of a workflow (`snakemake learning`), for the diagnostics that replay one by
hand (diagnose_tdmpc.py, diagnose_sb3.py): the settings its rule would pass, resolved from the workflow's config."""
from __future__ import annotations

from pathlib import Path

from dswm import settings as S
from dswm.config import load_yaml
from dswm.pipeline.setup import load_tensor, set_up
from dswm.settings import EvaluationSettings, Runtime

STAGES = {"train": (S.learning_train_slice, "runtime", Runtime),
          "score": (S.learning_score_slice, "evaluation", EvaluationSettings)}
"""stage -> (its job slice, the slice's settings key, their class): the learning_train and learning_score jobs."""


def learning_job(root: Path, profile: str, method: str, stage: str):
    """The ``stage`` ("train" or "score") job of ``method``'s learning curve under ``profile``, set up as its rule
    sets it up (the calibration record read where the workflow wrote one).

    Returns:
        (the JobSetup, the prepared tensor of learning.dataset, the learning settings, the job's slice).
    """
    slice_of, key, cls = STAGES[stage]
    config = load_yaml(root / "config.yaml")
    config["profile"] = profile
    settings = S.resolve(config, root=root, schema=root / "workflow" / "schemas" / "config.schema.yaml")
    learning = S.learning_settings(config, profile)
    job = slice_of(settings, learning, method)
    intensity = root / "results" / "calibration" / "demand_intensity.json"
    s = set_up(job, key, cls, intensity if intensity.exists() else None)
    return s, load_tensor(root / "results" / "data" / learning.dataset), learning, job
