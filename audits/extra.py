"""Protocol family, part 5: the figures' extra runs train on training days and evaluate the model they trained.

* `check_extra_runs`: every extra run the figures draw (``results/extra/<dataset>/<variant>/<method>/seed<seed>/``:
  the do(s) probe and the scaling sweeps, the foresight grid, the headroom map; ``dswm.settings.extra_jobs``,
  ``foresight_jobs``, ``headroom_jobs``, derived from the settings) hashes to the content record its evaluate job
  wrote last; a learning method's run records the model it loaded, which is its training source's: the one
  ``extra_train`` fitted under the variant where the variant changes training, else the main train job's; that
  model hashes to the SHA-256 its training manifest records and the evaluation loaded, and the manifest (for an
  ``extra_train`` run) declares no test data read and records training days only. A method that does not learn
  loaded no model.

The tables' audit leaves these files out (its inputs stay the tables' sources); the figures' extra audit
(results/audit/extra.json, the `audit_extra` rule, run by `figures` and `audit`) reads them.
"""
from __future__ import annotations

from pathlib import Path

from audits.context import AuditContext, AuditInputError
from audits.protocol import result_record, verify_record
from audits.report import Check
from audits.training import MODEL_FILE, _under_root, declares_no_test_data, manifest_days, verify_loaded_model

EXTRA_LEFT_OUT = ("the figures' extra runs are not read by this audit, whose inputs are the tables' sources alone: "
                  "the extra audit (results/audit/extra.json, the `audit_extra` rule, run by `figures` and `audit`) "
                  "checks them")
"""The evidence note of the check in an audit that leaves the extra runs out (``AuditContext.read_extra``)."""


def extra_runs(ctx: AuditContext) -> list[tuple[str, str, str, int, bool]]:
    """(dataset, variant name, method, seed, whether the variant retrains the method) of every extra run the
    profile's figures draw: the list the workflow gives the audit (``AuditContext.extra_runs``, the `audit_extra`
    rule's, from ``dswm.settings.variant_retrains`` under its full settings), else derived from the settings' figures
    section (``python -m audits``, whose settings are whole).

    Raises:
        AuditInputError: neither is there (the workflow's audit slice carries no figures section).
    """
    from dswm import settings as S

    if ctx.extra_runs is not None:
        return [(str(d), str(v), str(m), int(seed), bool(r)) for d, v, m, seed, r in ctx.extra_runs]
    s = ctx.settings
    if s.figures is None:
        raise AuditInputError("the audit's settings carry no figures section and no list of extra runs was given: "
                              "which extra runs the figures draw is unknown (the audit_extra rule passes them)")
    jobs = [(s.figures.dataset, v, m, seed) for v, m, seed in S.extra_jobs(s)]
    jobs += S.foresight_jobs(s) + S.headroom_jobs(s)
    return [(d, v, m, int(seed), ctx.learns(m) and S.variant_retrains(s, m, S.parse_variant(v)))
            for d, v, m, seed in dict.fromkeys(jobs)]


def extra_dir(ctx: AuditContext, ds: str, variant: str, method: str, seed: int) -> Path:
    """The directory of one extra run (workflow/rules/extra.smk, ``EXTRA_DIR``)."""
    return ctx.results / "extra" / ds / variant / method / f"seed{seed}"


def _loaded_model(chk: Check, ctx: AuditContext, ds: str, variant: str, method: str, seed: int, retrained: bool,
                  days: Path) -> dict | None:
    """A learning method's extra evaluation loaded its training source's model, unchanged since training (the
    extra_train manifest's days checked too); the evidence, or None after a finding that stops the check."""
    from dswm.protocol.evaluation import MODEL_RECORD_KEY, read_model_record

    where = ctx.rel(days)
    job = f"{ds}/{variant}/{method}/seed{seed}"
    rec = result_record(ctx, chk, days, read=read_model_record, key=MODEL_RECORD_KEY,
                        holds="the model file the evaluation loaded, its SHA-256 and its training source", job=job)
    if rec is None:
        return None
    if not ctx.learns(method):
        if rec.get("model") is not None:
            chk.fail(f"{where}: records loading model {rec['model']!r}, but {method} does not learn")
        return {"model": None}
    source = ctx.training_source(method)
    run = extra_dir(ctx, ds, variant, source, seed) if retrained else ctx.run_dir(ds, source, seed)
    want_model, want_manifest = run / MODEL_FILE, run / "train_manifest.json"
    if not rec.get("model") or _under_root(ctx, rec["model"]).resolve() != want_model.resolve():
        chk.fail(f"{where}: model = {rec.get('model')!r}, expected {ctx.rel(want_model)}, the model "
                 f"{'extra_train fitted under ' + variant if retrained else 'the main train job fitted'}")
        return None
    try:
        man = ctx.ledger.read_json(want_manifest)
    except FileNotFoundError:
        chk.fail(f"{ctx.rel(want_manifest)}: missing; {where} evaluated the model it describes")
        return None
    except ValueError as exc:
        chk.fail(f"{ctx.rel(want_manifest)}: not valid JSON ({exc})")
        return None
    mwhere = ctx.rel(want_manifest)
    if retrained:  # the main train jobs' manifests are the tables' audit's (protocol.training_days, checkpoints)
        manifest_days(chk, ctx, ds, man, where=mwhere, method=source)
        declares_no_test_data(chk, man, mwhere)
    train_job = f"{ds}/{variant}/{source}/seed{seed}" if retrained else f"{ds}/{source}/seed{seed}"
    if verify_loaded_model(chk, ctx, where=where, rec=rec, mpath=want_model, want_model=want_model,
                           manifest=want_manifest, man=man, method=method, source=source,
                           train_job=train_job) is None:
        return None
    return {"model": ctx.rel(want_model), "fitted_by": "extra_train" if retrained else "train",
            "training_days": len(set(man.get("days") or [])) if retrained else "checked by protocol.training_days"}


def check_extra_runs(ctx: AuditContext) -> Check:
    """The figures' extra runs are unchanged since evaluation and evaluate models trained on training days."""
    chk = Check(id="protocol.extra_runs", family="protocol",
                claim="Every extra run the figures draw (do(s) probe, scaling sweeps, foresight grid, headroom map) "
                      "hashes to the content record its evaluate job wrote last; a learning method's run loaded "
                      "its training source's model (extra_train's where the variant changes training, else the "
                      "main train job's), which hashes to the SHA-256 its training manifest records and the "
                      "evaluation took, and an extra_train manifest declares no test data read and records training "
                      "days only; a method that does not learn loaded no model.")
    if not ctx.read_extra:
        chk.evidence["note"] = EXTRA_LEFT_OUT
        return chk
    try:
        jobs = extra_runs(ctx)
    except AuditInputError as exc:
        chk.fail(str(exc))
        return chk
    if not jobs:
        chk.evidence["note"] = "the profile's figures draw no extra run"
        return chk
    chk.evidence["runs"], absent = {}, []
    for ds, variant, method, seed, retrains in jobs:
        run = extra_dir(ctx, ds, variant, method, seed)
        days = run / "days.parquet"
        if not days.is_file():
            absent.append(ctx.rel(days))
            continue
        job = f"{ds}/{variant}/{method}/seed{seed}"
        fix = (f"delete the result files of {job} ({ctx.rel(run)}/) and run `snakemake --cores 2 figures "
               f"--config profile={ctx.profile}` to regenerate them")
        try:
            record = verify_record(chk, ctx, run, job=job, fix=fix)
            model = _loaded_model(chk, ctx, ds, variant, method, seed, retrains, days)
        except AuditInputError as exc:
            chk.fail(str(exc))
            continue
        same = record is not None and all(v["recorded"] == v["found"] for v in record.values())
        chk.evidence["runs"][job] = {"content": "hashes as recorded" if same else record, "model": model}
    if absent:
        chk.evidence["not_yet_run"] = absent
    return chk
