"""Runs every check under the read-only guard, proves nothing changed, and writes the report.

`run_audit` returns the report dict; `write_report` (audits.report) writes it; `gate` decides whether a written
report lets tables be built: it passed, it audits the current profile and settings (`report_identity`), and
every file it vouches for still hashes to the value the audit took.
"""
from __future__ import annotations

import json
import logging
import traceback
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

from audits import bounds, crop, derived, extra, learning, probes, protocol, splits, sql, statistics, training
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
    sql.check_sql_crop,
    sql.check_sql_normalizer,
    sql.check_sql_tensor,
    derived.check_week,
    crop.check_crop,
    derived.check_initial_positions,
    derived.check_calibration,
    protocol.check_hashes,
    protocol.check_result_days,
    protocol.check_result_records,
    protocol.check_bcd_search_identical,
    bounds.check_clairvoyant_bounds,
    training.check_training_days,
    training.check_checkpoints,
    training.check_evaluated_models,
    probes.check_probes_out_of_tables,
    learning.check_learning_days,
    extra.check_extra_runs,
]
"""Every check, in report order (families: splits, statistics, protocol)."""

PARTS = ("probes", "learning", "extra")
"""The files outside the tables' sources an audit may read: the sample-efficiency probe's (results/probes/), the
learning runs (results/learning/) and the figures' extra runs (results/extra/)."""
SCOPES: dict[str, tuple[list[Callable[[AuditContext], Check]], frozenset[str]]] = {
    "all": (CHECKS, frozenset(PARTS)),
    "tables": (CHECKS, frozenset()),
    "probes": ([probes.check_probes_out_of_tables], frozenset({"probes"})),
    "learning": ([learning.check_learning_days], frozenset({"learning"})),
    "extra": ([extra.check_extra_runs], frozenset({"extra"})),
}
"""Audit scope -> (its checks, the parts of :data:`PARTS` it reads). `all`: the whole audit in one report (`python -m
audits`). The workflow splits it in reports that each rest on the files of their own target: `tables` (the
`audit_report` rule, the tables' gate) runs every check over the tables' sources and reads none of the parts;
`probes` (the `audit_probes` rule, which `figures` runs) compares the probe files with the tables' sources; `extra`
(the `audit_extra` rule, which `figures` runs) checks the figures' extra runs; `learning` (the `audit_learning`
rule, which `learning` runs) checks the days of the learning runs under results/learning/."""


def _run_one(fn: Callable[[AuditContext], Check], ctx: AuditContext) -> Check:
    """Runs one check; a check that crashes is a failed check (the audit never passes on an error)."""
    name = fn.__name__.removeprefix("check_")
    family = fn.__module__.split(".")[-1]
    family = {"derived": "statistics", "crop": "statistics", "sql": "statistics", "training": "protocol",
              "probes": "protocol", "bounds": "protocol",
              "learning": "protocol", "extra": "protocol"}.get(family, family)
    try:
        return fn(ctx)
    except Exception as exc:  # noqa: BLE001 - reported as a failed check, with its traceback
        log.exception("audit check %s crashed", name)
        chk = Check(id=f"{family}.{name}", family=family, claim=(fn.__doc__ or "").strip().splitlines()[0])
        chk.fail(f"the check could not run: {type(exc).__name__}: {exc}")
        chk.evidence["traceback"] = traceback.format_exc().splitlines()[-6:]
        return chk


def run_audit(*, root: Path | str, settings: Settings, extra_reads: list[Path] | None = None,
              scope: str = "all", extra_runs: list | None = None) -> dict:
    """Runs the audit of `scope` on the tree under `root`.

    Args:
        root: the workflow's working directory (holds results/).
        settings: the settings the pipeline ran under (config.yaml plus overrides, resolved once).
        extra_reads: files read outside the checks (config.yaml) to include in the read-only proof.
        scope: a key of :data:`SCOPES` (default: the whole audit).
        extra_runs: (dataset, variant, method, seed) of every extra run the figures draw, as the workflow lists
            them (None: from the settings' figures section, which the workflow's audit slice leaves out).
    Returns:
        The report (see audits.report.build_report); report["passed"] is the verdict.
    """
    import torch

    if scope not in SCOPES:
        raise ValueError(f"audit scope {scope!r}: expected one of {', '.join(SCOPES)}")
    checks_of_scope, parts = SCOPES[scope]
    torch.set_num_threads(settings.evaluation.torch_threads)  # as every evaluation job
    root = Path(root).resolve()
    ledger = ReadLedger(root=root, guarded=[root])
    for p in extra_reads or []:
        ledger.track(p)
    ctx = AuditContext(root=root, settings=settings, ledger=ledger, read_probes="probes" in parts,
                       read_learning="learning" in parts, read_extra="extra" in parts, extra_runs=extra_runs)
    checks = []
    with ledger.guard():
        for fn in checks_of_scope:
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
    header = {**report_identity(settings), "scope": scope, "datasets": ctx.datasets, "methods": ctx.methods,
              "settings_files": [ledger.rel(p) for p in extra_reads or []]}
    return build_report(checks=checks, read_only=ro, header=header)


def report_identity(settings: Settings) -> dict:
    """{"profile", "config_hash"} the report of an audit under `settings` carries.

    `config_hash` is the hash of the audit's settings (`dswm.settings.audit_slice`, rebuilt as the audit_report
    rule's job rebuilds it), so the workflow and `python -m audits` give one config.yaml one hash, and the tables
    rule can compute, from its own settings, the identity the report must carry.
    """
    from dswm.settings import Settings, audit_slice, param, read_param

    audited = Settings.from_plain(read_param(param(audit_slice(settings))))
    return {"profile": audited.profile, "config_hash": audited.hash()}


def gate(report_json: Path | str, *, expect: Mapping[str, Any] | None = None,
         root: Path | str | None = None, target: str = "tables") -> list[str]:
    """Why a written report does not let tables be built (empty = it does).

    Args:
        report_json: the report (results/audit/report.json).
        expect: {"profile", "config_hash"} of the current settings (`report_identity`); the report must carry
            both, or it belongs to another run.
        root: the workflow's working directory; every file the report vouches for (`read_only.files`: `path`,
            `sha256_after`) must still hash to the value the audit took, the settings files aside (the
            config_hash vouches for the settings). Not checked when None.
        target: the Snakemake target whose call audits the tree afresh (named in the messages): `tables` for the
            main report, `figures` for the probe report.
    Returns:
        One message per reason, each naming the file and what to do. A report of another profile or other
        settings, or one that cannot be read, yields only that; a failed audit yields a summary, then each
        finding as "<check id>: <finding>"; otherwise each vouched file that is missing or changed.
    """
    where = str(report_json)
    profile = (expect or {}).get("profile")
    cmd = f"`snakemake --cores 2 {target}" + (f" --config profile={profile}" if profile else "") + "`"
    redo = f"delete {where} and run {cmd} to audit the tree afresh"
    try:
        with open(report_json, "r", encoding="utf-8") as fh:
            report = json.load(fh)
    except OSError as exc:
        return [f"{where}: cannot be read ({exc.strerror or exc}); {redo}"]
    except ValueError as exc:
        return [f"{where}: not valid JSON ({exc}); {redo}"]
    need = ["passed", "checks", *(["profile", "config_hash"] if expect is not None else []),
            *(["read_only"] if root is not None else [])]
    missing = [k for k in need if not isinstance(report, dict) or k not in report]
    if missing:
        return [f"{where}: not an audit report (lacks {', '.join(repr(k) for k in missing)}); {redo}"]
    if not isinstance(report["checks"], list) or not all(
            isinstance(c, dict) and {"id", "passed", "failures"} <= set(c) for c in report["checks"]):
        return [f"{where}: 'checks' is not a list of {{id, passed, failures}}; {redo}"]
    if expect is not None:
        wrong = []
        if report["profile"] != expect["profile"]:
            wrong.append(f"{where}: audits profile {report['profile']!r}, but the tables are built for profile "
                         f"{expect['profile']!r} — the report belongs to another run; {redo}")
        if report["config_hash"] != expect["config_hash"]:
            wrong.append(f"{where}: config_hash = {report['config_hash']!r}, but the current settings hash to "
                         f"{expect['config_hash']!r} — the report audits other settings; {redo}")
        if wrong:
            return wrong
    failing = [f"{c['id']}: {m}" for c in report["checks"] if not c["passed"] for m in c["failures"]]
    if not report["passed"] or failing:
        md = Path(where).with_suffix(".md")
        what = "no table is built from" if target == "tables" else f"`{target}` does not pass on"
        return [f"{where}: the leakage audit failed ({len(failing)} finding(s)); {what} a "
                f"pipeline that fails it — fix each finding (below, and in {md}), then run {cmd}"] + failing
    return _vouched(report, where=where, root=Path(root), redo=redo) if root is not None else []


def _vouched(report: dict, *, where: str, root: Path, redo: str) -> list[str]:
    """Every file the report vouches for that is missing or now hashes differently (settings files aside)."""
    from prep.rawio import sha256_file

    files = report["read_only"].get("files") if isinstance(report["read_only"], dict) else None
    if not isinstance(files, list):
        return [f"{where}: read_only.files = {files!r}; expected the list of {{path, sha256_after}} of every file "
                f"the audit read; {redo}"]
    skip = set(report.get("settings_files") or [])
    out = []
    for i, entry in enumerate(files):
        if not (isinstance(entry, dict) and isinstance(entry.get("path"), str) and
                isinstance(entry.get("sha256_after"), str)):
            out.append(f"{where}: read_only.files[{i}] = {entry!r}; expected {{path, sha256_after}}; {redo}")
            continue
        if entry["path"] in skip:
            continue
        path = Path(entry["path"]) if Path(entry["path"]).is_absolute() else root / entry["path"]
        if not path.is_file():
            out.append(f"{entry['path']}: missing, but {where} vouches for it (SHA-256 {entry['sha256_after']}) — "
                       f"the audited tree changed after the audit; {redo}")
        elif (now := sha256_file(path)) != entry["sha256_after"]:
            out.append(f"{entry['path']}: SHA-256 is {now}, {where} vouches for {entry['sha256_after']} — the file "
                       f"changed after the audit; {redo}")
    return out
