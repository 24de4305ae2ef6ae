"""The figures beside the runs they show: a figure rule logs its PNG and PDF as artifacts of those runs."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping, Sequence

from dswm.pipeline.tracking.client import retry, workdir_tag
from dswm.pipeline.tracking.store import run_experiments, store_client


def attach_figures(*, mlflow_cfg: Mapping[str, Any], paths: Sequence[str | Path], stage: str | Sequence[str],
                   datasets: Sequence[str] | None = None, methods: Sequence[str] | None = None,
                   profile: str | None = None, artifact_path: str = "figures") -> int:
    """Log the figure files ``paths`` as artifacts (under ``artifact_path``) of every FINISHED run of this working
    directory they concern: the runs of ``stage`` (one or several), restricted to ``datasets``, ``methods`` and
    ``profile`` where given.

    A figure is drawn after the runs it shows have ended; MLflow keeps a run's artifact store open after that, so
    the figure lands beside the run's result files. Returns how many runs received the files.
    """
    client = store_client(mlflow_cfg)
    _, both = run_experiments(client, mlflow_cfg, "main")  # a figure shows main runs, the figures' runs, or both
    stages = [stage] if isinstance(stage, str) else list(stage)
    # tags allow no IN; the stages are chosen below
    query = f"attributes.status = 'FINISHED' and tags.workdir = '{workdir_tag()}'"
    if profile is not None:
        query += f" and tags.profile = '{profile}'"
    runs = retry(client.search_runs, both, filter_string=query, max_results=50000)
    chosen = [r for r in runs if r.data.tags.get("stage") in stages
              and (datasets is None or r.data.tags.get("dataset") in datasets)
              and (methods is None or r.data.tags.get("method") in methods)]
    for r in chosen:
        for p in paths:
            retry(client.log_artifact, r.info.run_id, str(p), artifact_path)
    return len(chosen)


def attach_figure_outputs(attach: Mapping[str, Any], out: Mapping[str, str | Path]) -> int:
    """A figure rule's side of ``figure_attach`` (workflow/rules/common.smk): log the PNG and PDF of ``out`` beside
    the runs ``attach`` (the value of that Untracked param) names; returns how many runs received them."""
    sel = attach
    return attach_figures(mlflow_cfg=sel["mlflow"], paths=[out["png"], out["pdf"]], stage=sel["stages"],
                          datasets=sel["datasets"], methods=sel["methods"], profile=sel["profile"])
