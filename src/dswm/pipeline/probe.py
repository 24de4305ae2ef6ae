"""The ``probe`` job (workflow/rules/probes.smk): every model snapshot of one train job evaluated on the probe's
fixed test day (``dswm.protocol.probe``), written apart from every table's source and tracked in MLflow with stage
"probe"."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

import polars as pl

from dswm.methods import snapshots
from dswm.pipeline.jobs import DAY_METRICS
from dswm.pipeline.setup import load_tensor, open_run, score_snapshot, set_up, workdir_relative
from dswm.protocol import probe
from dswm.settings import Display, EvaluationSettings
from prep.atomic import atomic_path, write_json
from prep.rawio import sha256_file


def probe_job(*, job: Mapping[str, Any], mlflow_cfg: Mapping[str, Any], display: Display, tensor_dir: str | Path,
              dataset: str, method: str, seed: int, snapshots_dir: str | Path, evaluation: str | Path | None,
              out: str | Path, record_out: str | Path, repo: str | Path,
              intensity: str | Path | None = None) -> pl.DataFrame:
    """Evaluate every snapshot of ``snapshots_dir`` on the probe day; write ``out`` (probe.parquet), then its
    content record ``record_out``; track it in MLflow (stage "probe", metrics ``probe/<metric>`` against the
    transitions consumed).

    Args:
        job: the plain form of ``dswm.settings.probe_slice`` (the method with all its settings, as its evaluation).
        mlflow_cfg: the ``mlflow`` section (``dswm.settings.tracking``): where the run is logged.
        display: how the job reports progress.
        snapshots_dir: the train rule's ``snapshots`` output of (dataset, method, seed), with its index.json.
        evaluation: the days.parquet of the same job's evaluation (None: none): its value on the probe day is
            recorded in every row (``evaluated_sr_mean``), so the audit tells the evaluation's own number from a
            probe number.
        intensity: the calibrate rule's record, when ``scenario.demand_intensity`` is ``calibrate``.

    Each snapshot is loaded into a fresh controller and evaluated alone on the one day (the evaluation seeds torch
    and numpy with ``seed`` each time), so a snapshot's number does not depend on the others.

    Returns:
        The probe rows: the evaluation's per-day columns (``split`` = "probe") and ``dswm.protocol.probe``'s
        PROBE_COLUMNS, one row per requested fraction, in order.
    """
    s = set_up(job, "evaluation", EvaluationSettings, intensity)
    tensor = load_tensor(tensor_dir)
    day = probe.probe_day(tensor)
    entries = snapshots.read_index(snapshots_dir)
    evaluated = None
    if evaluation is not None:
        on_day = pl.read_parquet(evaluation).filter(pl.col("day") == day)["sr_mean"]
        evaluated = float(on_day[0]) if len(on_day) else None
    with open_run(s, mlflow_cfg=mlflow_cfg, stage="probe", dataset=dataset, method=method, seed=seed, repo=repo,
                  keep=[out], kind="probe") as run:
        run.set_tags({"probe_day": tensor.labels[day], "diagnostic_only": "true",
                      "snapshots": workdir_relative(snapshots_dir)})
        scored: dict[str, dict] = {}
        rows = []
        for e in entries:
            if e["sha256"] not in scored:  # fractions reached at the same unit share one snapshot
                scored[e["sha256"]] = score_snapshot(
                    s, tensor=tensor, method=method, seed=seed, path=e["path"], days={probe.PROBE_SPLIT: [day]},
                    progress_interval_s=display.progress_mininterval_s).row(0, named=True)
            row = dict(scored[e["sha256"]])
            rows.append({**row, "probe": True, "fraction": float(e["fraction"]),
                         "fraction_done": float(e["fraction_done"]), "done": int(e["done"]), "total": int(e["total"]),
                         "n_transitions": int(e["n_transitions"]), "final": int(e["done"]) == int(e["total"]),
                         "snapshot": workdir_relative(e["path"]), "snapshot_sha256": e["sha256"],
                         "evaluated_sr_mean": evaluated})
            run.log_metrics({f"probe/{k}": row[k] for k in DAY_METRICS if row.get(k) is not None},
                            step=int(e["n_transitions"]))
        frame = pl.DataFrame(rows).with_columns(pl.col("day").cast(pl.Int32), pl.col("seed").cast(pl.Int32),
                                                pl.col("evaluated_sr_mean").cast(pl.Float64))
        with atomic_path(out) as tmp:
            frame.write_parquet(tmp)
        run.log_artifact(out)
    write_json(record_out, {"files": {probe.PROBE_FILE: {"sha256": sha256_file(Path(out)),
                                                         "bytes": Path(out).stat().st_size}},
                            "dataset": dataset, "method": method, "seed": int(seed), "day": int(day),
                            "label": tensor.labels[day],
                            "snapshots": [{k: e[k] for k in ("fraction", "file", "sha256")} for e in entries]})
    return frame
