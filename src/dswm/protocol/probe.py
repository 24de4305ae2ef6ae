"""The sample-efficiency probe (paper Section V-E, Fig. sample): a fixed test-day probe of the model snapshots a
training run took at fixed fractions of its budget (``dswm.methods.snapshots``).

Protocol, as the paper states it: one fixed day (the first ID test day of ``figures.dataset``), every snapshot of
the fixed training budget evaluated there in the evaluation's own environment, initial fleet and observation
(``dswm.protocol.evaluation.evaluate``), no early stopping and no model selection (the trained model is the last
snapshot whatever the probe says). The probe's numbers are diagnostic only: they are written under
``results/probes/`` (:func:`probe_path`), never beside a table's source, and every row carries marks no result file
has (:data:`PROBE_SPLIT` in ``split``, the :data:`PROBE_COLUMNS`), so the audit (``audits.probes``) can prove that
none reached a table.
"""
from __future__ import annotations

from pathlib import Path

PROBE_DIR = "results/probes"
"""Where every probe file lives (outside ``results/<dataset>/``, the tables' sources)."""
PROBE_FILE = "probe.parquet"
"""One probe file per (dataset, method, seed): ``PROBE_DIR/<dataset>/<method>/seed<seed>/probe.parquet``."""
PROBE_RECORD_FILE = "probe_manifest.json"
"""The content record a probe job writes last beside its probe file: {"files": {"probe.parquet": {"sha256",
"bytes"}}, "day", "label", "snapshots": [...]}."""
PROBE_SPLIT = "probe"
"""The ``split`` of every probe row (a result file's rows are "id" or "ood")."""
PROBE_COLUMNS = ("probe", "fraction", "fraction_done", "done", "total", "n_transitions", "final", "snapshot",
                 "snapshot_sha256", "evaluated_sr_mean")
"""The columns a probe file adds to the evaluation's per-day columns: ``probe`` (always true), the requested budget
``fraction``, the budget actually done at the snapshot (``fraction_done`` = ``done`` / ``total`` units), the
environment transitions consumed by then (``n_transitions``), ``final`` (the snapshot of the last unit: the trained
model), the snapshot file and its SHA-256, and ``evaluated_sr_mean``: what the probed job's evaluation (its
days.parquet) scored on the probe day when the probe ran (null when it does not evaluate that day). A row whose
``sr_mean`` equals it is the evaluation's own number; any other is a probe number, which no table may hold. No result
file of a table has any of these columns."""


def probe_path(dataset: str, method: str, seed: int) -> str:
    """The probe file of one (dataset, method, seed), relative to the workflow's root."""
    return f"{PROBE_DIR}/{dataset}/{method}/seed{seed}/{PROBE_FILE}"


def probe_day(tensor) -> int:
    """The probe's fixed day: the first ID test day of the dataset (``meta.json`` ``eval_days.id[0]``).

    Raises:
        ValueError: the dataset has no ID test day.
    """
    days = [int(d) for d in tensor.eval_days("id")]
    if not days:
        raise ValueError(f"meta.json of {tensor.meta['dataset']}: eval_days.id is empty; the probe needs the first "
                         f"ID test day")
    return days[0]


def is_probe_file(path: str | Path) -> bool:
    """True for a file named like a probe file (:data:`PROBE_FILE`)."""
    return Path(path).name == PROBE_FILE
