"""Runs every check under the read-only guard, proves nothing changed, and writes the report.

`run_audit` returns the report dict; `write_report` (audits.report) writes it; `gate` turns a written report
into the pass/fail decision the `audit` target enforces.
"""
from __future__ import annotations

import json
import logging
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from audits import crop, derived, protocol, splits, statistics, training
from audits.context import AuditContext
from audits.ledger import ReadLedger
from audits.report import Check, build_report

if TYPE_CHECKING:
    from dswm.settings import Settings

log = logging.getLogger(__name__)

CHECKS: list[Callable[[AuditContext], Check]] = [
    splits.check_segments,
    splits.check_eval_days,
    statistics.check_p99,
    statistics.check_kappa,
    statistics.check_tensor,
    statistics.check_not_all_days,
    derived.check_week,
    crop.check_crop,
    derived.check_initial_positions,
    derived.check_calibration,
    protocol.check_hashes,
    protocol.check_result_days,
    protocol.check_bcd_search_identical,
    training.check_training_days,
    training.check_checkpoints,
    training.check_evaluated_models,
]
"""Every check, in report order (families: splits, statistics, protocol)."""


def _run_one(fn: Callable[[AuditContext], Check], ctx: AuditContext) -> Check:
    """Runs one check; a check that crashes is a failed check (the audit never passes on an error)."""
    name = fn.__name__.removeprefix("check_")
    family = fn.__module__.split(".")[-1]
    family = {"derived": "statistics", "crop": "statistics", "training": "protocol"}.get(family, family)
    try:
        return fn(ctx)
    except Exception as exc:  # noqa: BLE001 - reported as a failed check, with its traceback
        log.exception("audit check %s crashed", name)
        chk = Check(id=f"{family}.{name}", family=family, claim=(fn.__doc__ or "").strip().splitlines()[0])
        chk.fail(f"the check could not run: {type(exc).__name__}: {exc}")
        chk.evidence["traceback"] = traceback.format_exc().splitlines()[-6:]
        return chk


def run_audit(*, root: Path | str, settings: Settings, extra_reads: list[Path] | None = None) -> dict:
    """Runs the whole audit on the tree under `root`.

    Args:
        root: the workflow's working directory (holds results/).
        settings: the settings the pipeline ran under (config.yaml plus overrides, resolved once).
        extra_reads: files read outside the checks (config.yaml) to include in the read-only proof.
    Returns:
        The report (see audits.report.build_report); report["passed"] is the verdict.
    """
    import torch

    torch.set_num_threads(settings.evaluation.torch_threads)  # as every evaluation job
    root = Path(root).resolve()
    ledger = ReadLedger(root=root, guarded=[root])
    for p in extra_reads or []:
        ledger.track(p)
    ctx = AuditContext(root=root, settings=settings, ledger=ledger)
    checks = []
    with ledger.guard():
        for fn in CHECKS:
            log.info("audit: %s", fn.__name__)
            chk = _run_one(fn, ctx)
            log.info("audit: %s %s", chk.id, "pass" if chk.passed else f"FAIL ({len(chk.failures)} findings)")
            checks.append(chk)
    ro = ledger.verify()
    proof = Check(id="read-only.unchanged", family="read-only",
                  claim="Every file the audit read has the same SHA-256, size and modification time after the "
                        "audit as before its first read, and no write-mode open of the audited tree happened.")
    for p in ro["changed"]:
        proof.fail(f"{p}: changed while the audit ran")
    for msg in ro["write_attempts"]:
        proof.fail(msg)
    proof.evidence = {"files_read": len(ro["files"]), "changed": len(ro["changed"])}
    checks.append(proof)
    header = {"profile": ctx.profile, "datasets": ctx.datasets, "methods": ctx.methods,
              "config_hash": settings.hash()}
    return build_report(checks=checks, read_only=ro, header=header)


def gate(report_json: Path | str) -> list[str]:
    """The failing checks of a written report (empty = the audit passed).

    Raises:
        ValueError: the report is missing its verdict.
    """
    with open(report_json, "r", encoding="utf-8") as fh:
        report = json.load(fh)
    if "passed" not in report or "checks" not in report:
        raise ValueError(f"{report_json}: not an audit report (expected keys 'passed' and 'checks')")
    failing = [f"{c['id']}: {m}" for c in report["checks"] if not c["passed"] for m in c["failures"]]
    if not report["passed"] and not failing:
        failing = [f"{report_json}: verdict is fail"]
    return failing
