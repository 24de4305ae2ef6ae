"""Protocol family, part 1: every method is measured in the same world.

* `check_hashes`: every result file of every method carries one observation-spec hash, one eval-days hash
  and one scenario hash, each equal to the value recomputed from the settings and meta.json.
* `check_result_days`: every result file holds exactly the configured ID and OOD days of its dataset.
* `check_bcd_search_identical`: every result file records its method's resolved settings, and every method that
  runs a block-coordinate-descent search ran the one search the settings give it, identical across the run.
* `check_result_records`: every result file hashes to the content record (eval_manifest.json) its evaluate job
  wrote last, so none changed after its evaluation, whatever its file time says.

Part 2, that learners learn from training days only and evaluate the model they trained, is `audits.training`.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import polars as pl

from audits.context import AuditContext, AuditInputError
from audits.hashes import expected_hashes, expected_result_days
from audits.report import Check

HASH_COLUMNS = ("obs_spec_hash", "eval_days_hash", "scenario_hash")
RESULT_COLUMNS = ("day", "label", "split", "sr_mean", *HASH_COLUMNS, "seed", "method", "dataset")
HASH_LEAK = {"obs_spec_hash": "a different observation spec", "eval_days_hash": "different eval days",
                    "scenario_hash": "different scenario constants"}


def _read_result(ctx: AuditContext, path: Path) -> pl.DataFrame:
    try:
        return pl.read_parquet(ctx.ledger.track(path))
    except FileNotFoundError as exc:
        raise AuditInputError(f"{ctx.rel(path)}: result file missing (run the evaluate rule)") from exc
    except (OSError, pl.exceptions.PolarsError) as exc:
        raise AuditInputError(f"{ctx.rel(path)}: unreadable ({exc})") from exc


def result_path(ctx: AuditContext, ds: str, method: str, seed: int) -> Path:
    return ctx.run_dir(ds, method, seed) / "days.parquet"


def result_record(ctx: AuditContext, chk: Check, path: Path, *, read, key: str, holds: str, job: str) -> dict | None:
    """One metadata record of a result file, or None after failing ``chk`` with the reason (missing file,
    unreadable file, no record).

    Args:
        read: the reader of the record (``read_model_record`` or ``read_method_record``); key: its metadata key;
        holds: what the record should hold (for the message); job: "dataset/method/seed<seed>" to re-run.
    """
    where = ctx.rel(path)
    try:
        rec = read(ctx.ledger.track(path))
    except FileNotFoundError:
        chk.fail(f"{where}: result file missing (run the evaluate rule)")
        return None
    except (OSError, ValueError, pl.exceptions.PolarsError) as exc:
        chk.fail(f"{where}: unreadable ({exc})")
        return None
    if rec is None:
        chk.fail(f"{where}: no {key} record in its metadata; expected {holds} — the result predates this record; "
                 f"re-run the evaluate job of {job}")
    return rec


def _results(ctx: AuditContext, chk: Check, ds: str):
    """(method, seed, path, table) of every result file of ``ds``; a missing or unreadable one fails ``chk``."""
    for method in ctx.methods_on(ds):
        for seed in ctx.seeds(ds):
            path = result_path(ctx, ds, method, seed)
            try:
                df = _read_result(ctx, path)
            except AuditInputError as exc:
                chk.fail(str(exc))
                continue
            yield method, seed, path, df


def check_hashes(ctx: AuditContext) -> Check:
    """Same observation-spec, eval-days and scenario hashes in every result file, equal to the recomputed ones."""
    chk = Check(id="protocol.hashes", family="protocol",
                claim="Every result file of every method carries the observation-spec, eval-days and scenario "
                      "hashes recomputed from config.yaml and meta.json (one value per file).")
    for ds in ctx.datasets:
        try:
            want = expected_hashes(ctx, ds)
        except AuditInputError as exc:
            chk.fail(f"{exc} — the expected hashes cannot be recomputed")
            continue
        seen: dict[str, dict[str, list[str]]] = {c: {} for c in HASH_COLUMNS}
        for method, seed, path, df in _results(ctx, chk, ds):
            missing = [c for c in RESULT_COLUMNS if c not in df.columns]
            if missing:
                chk.fail(f"{ctx.rel(path)}: lacks column(s) {missing}")
                continue
            for col in ("dataset", "method", "seed"):
                vals = sorted(set(map(str, df[col].to_list())))
                own = {"dataset": ds, "method": method, "seed": str(seed)}[col]
                if vals != [own]:
                    chk.fail(f"{ctx.rel(path)}: column {col} holds {vals}, the path says {own!r}")
            for col in HASH_COLUMNS:
                vals = sorted(set(map(str, df[col].to_list())))
                for v in vals:
                    seen[col].setdefault(v, []).append(f"{method}/seed{seed}")
                if vals != [want[col]]:
                    chk.fail(f"{ctx.rel(path)}: {col} = {vals}, expected {want[col]} (recomputed from "
                             f"config.yaml and {ctx.rel(ctx.meta_path(ds))}) — {method} was run with "
                             f"{HASH_LEAK[col]}")
        chk.evidence[ds] = {"expected": want, "found": {c: {v: len(w) for v, w in s.items()} for c, s in seen.items()}}
    return chk


def check_result_days(ctx: AuditContext) -> Check:
    """Every result file evaluates exactly its dataset's configured ID and OOD days."""
    chk = Check(id="protocol.result_days", family="protocol",
                claim="Every result file holds exactly the configured ID and OOD days (as limited by the "
                      "profile), with their labels, and nothing else.")
    for ds in ctx.datasets:
        try:
            want = expected_result_days(ctx, ds)
            labels = {d["index"]: d["label"] for d in ctx.meta(ds)["days"]}
        except AuditInputError as exc:
            chk.fail(f"{exc} — the evaluated days cannot be verified")
            continue
        for method, seed, path, df in _results(ctx, chk, ds):
            if not {"day", "split"} <= set(df.columns):
                chk.fail(f"{ctx.rel(path)}: lacks the day/split columns")
                continue
            splits = sorted(set(df["split"].to_list()) - set(want))
            if splits:
                chk.fail(f"{ctx.rel(path)}: unknown split value(s) {splits}; expected id, ood")
            for split, days in want.items():
                got = sorted(int(d) for d in df.filter(pl.col("split") == split)["day"].to_list())
                if got != days:
                    chk.fail(f"{ctx.rel(path)}: split {split!r} evaluates days "
                             f"{[labels.get(d, d) for d in got]}, the configured {split.upper()} days are "
                             f"{[labels[d] for d in days]} — {method} evaluated on other days")
            if "label" in df.columns:
                wrong = [(int(d), lab) for d, lab in zip(df["day"].to_list(), df["label"].to_list())
                         if labels.get(int(d)) != lab]
                if wrong:
                    chk.fail(f"{ctx.rel(path)}: day index/label pairs {wrong[:3]} disagree with meta.json")
        chk.evidence[ds] = {k: [labels[d] for d in v] for k, v in want.items()}
    return chk


def _configured_searches(ctx: AuditContext, chk: Check) -> dict[str, Any]:
    """{method: the plain BCD search its controller runs under the settings, or None}, derived from the settings
    (the controller built as the evaluate job builds it, then ``search_settings()``); a method whose search cannot
    be derived fails ``chk`` and is left out."""
    from dswm.config import to_plain
    from dswm.methods import registry

    out: dict[str, Any] = {}
    for name in ctx.methods:
        m = ctx.settings.methods[name]
        try:
            ctrl = registry.build(name, target=m.target, options=m.options, seed=0,
                                  device=ctx.settings.evaluation.device)
            search = ctrl.search_settings()
        except Exception as exc:  # noqa: BLE001 - reported as a finding naming the method
            chk.fail(f"methods.{name}: the search settings of {m.target} cannot be derived from the settings "
                     f"({type(exc).__name__}: {exc})")
            continue
        out[name] = None if search is None else to_plain(search)
    return out


def _search_diff(a: Any, b: Any) -> str:
    """The keys in which two plain search settings differ, as "key: a vs b" (or the two values whole)."""
    if not (isinstance(a, dict) and isinstance(b, dict)):
        return f"{json.dumps(a, sort_keys=True)} vs {json.dumps(b, sort_keys=True)}"
    absent = "(absent)"
    keys = sorted(k for k in set(a) | set(b) if a.get(k, absent) != b.get(k, absent))
    return ", ".join(f"{k}: {json.dumps(a.get(k, absent))} vs {json.dumps(b.get(k, absent))}" for k in keys)


def check_bcd_search_identical(ctx: AuditContext) -> Check:
    """Every BCD search of the run (Greedy, the oracle, DSWM's proposal, ...) used identical search settings."""
    from dswm.protocol.evaluation import METHOD_RECORD_FIELDS, METHOD_RECORD_KEY, read_method_record

    chk = Check(id="protocol.bcd_search_identical", family="protocol",
                claim="Every result file of every method records its method's resolved settings "
                      f"({METHOD_RECORD_KEY}) for the method it holds; every method that runs a block-coordinate-"
                      "descent search recorded the search the settings give it, and all those searches are "
                      "identical (sweeps, lattice, refine, bandwidth logits), so no method's margin comes from a "
                      "stronger search.")
    want = _configured_searches(ctx, chk)
    runs: list[tuple[str, str, dict]] = []  # (file, method, plain search) of every result file that ran a BCD
    quiet: list[str] = []  # methods whose result files record no search
    for ds in ctx.datasets:
        for method in ctx.methods_on(ds):
            for seed in ctx.seeds(ds):
                path = result_path(ctx, ds, method, seed)
                where = ctx.rel(path)
                rec = result_record(ctx, chk, path, read=read_method_record, key=METHOD_RECORD_KEY,
                                    holds=f"the resolved settings and BCD search of {method}",
                                    job=f"{ds}/{method}/seed{seed}")
                if rec is None:
                    continue
                missing = [k for k in METHOD_RECORD_FIELDS if k not in rec]
                if missing:
                    chk.fail(f"{where}: {METHOD_RECORD_KEY} record lacks {missing}; expected the fields "
                             f"{list(METHOD_RECORD_FIELDS)}")
                    continue
                if rec["method"] != method:
                    chk.fail(f"{where}: {METHOD_RECORD_KEY} records method {rec['method']!r}, but the file is the "
                             f"result of {method!r} — the settings recorded are another method's")
                search = rec["search"]
                if search is not None and not isinstance(search, dict):
                    chk.fail(f"{where}: {METHOD_RECORD_KEY} search = {search!r}; expected the plain search "
                             f"settings (a JSON object) or null")
                    continue
                if method in want and search != want[method]:
                    chk.fail(f"{where}: {method} recorded search {json.dumps(search, sort_keys=True)}, the settings "
                             f"give {method} {json.dumps(want[method], sort_keys=True)} "
                             f"({_search_diff(search, want[method])}) — {method} was evaluated with other search "
                             f"settings than configured")
                if search is None:
                    quiet.append(method)
                else:
                    runs.append((where, method, search))
    quiet = [m for m in ctx.methods if m in quiet]
    if not runs:
        chk.evidence.update(search=None, methods=[], without_search=quiet,
                            note="no method of the run runs a BCD search (every result file records search null): "
                                 "nothing to compare")
        return chk
    variants: dict[str, list[tuple[str, str, dict]]] = {}
    for run in runs:
        variants.setdefault(json.dumps(run[2], sort_keys=True), []).append(run)
    # The reference is the search most result files ran (the first seen on a tie); every other one is named.
    ref_key = max(variants, key=lambda k: len(variants[k]))
    ref_where, ref_method, ref = variants[ref_key][0]
    for key, members in variants.items():
        if key == ref_key:
            continue
        for where, method, search in members:
            chk.fail(f"{where}: {method} ran the BCD search {key}, but {ref_where} ({ref_method}) ran {ref_key} — "
                     f"they differ in {_search_diff(search, ref)}; every BCD of a run must use the one search")
    ran = [m for m in ctx.methods if any(r[1] == m for r in runs)]
    chk.evidence.update(search=ref, methods=ran, files=len(runs), without_search=quiet)
    if len(variants) > 1:
        chk.evidence["variants"] = [{"search": json.loads(k), "files": [w for w, _, _ in v]}
                                    for k, v in variants.items()]
    return chk


def regenerate(ctx: AuditContext, ds: str, method: str, seed: int) -> str:
    """The fix for a result file that cannot be trusted: delete the job's result files and let the workflow
    evaluate it again (a missing result file is regenerated by the `tables` target)."""
    from dswm.protocol.evaluation import EVAL_OUTPUTS, EVAL_RECORD_FILE

    run = ctx.rel(ctx.run_dir(ds, method, seed))
    files = ",".join((*EVAL_OUTPUTS, EVAL_RECORD_FILE))
    return (f"delete the result files of {ds}/{method}/seed{seed} ({run}/{{{files}}}) and run "
            f"`snakemake --cores 2 tables --config profile={ctx.profile}` to regenerate them")


def check_result_records(ctx: AuditContext) -> Check:
    """Every result file hashes to the content record its evaluate job wrote last."""
    from dswm.protocol.evaluation import EVAL_OUTPUTS, EVAL_RECORD_FILE

    chk = Check(id="protocol.result_records", family="protocol",
                claim=f"Every result file ({', '.join(EVAL_OUTPUTS)}) of every job hashes to the SHA-256 its "
                      f"evaluate job recorded in {EVAL_RECORD_FILE}, which it writes last, once both are complete: "
                      f"no result file changed after its evaluation, whatever its file time says.")
    for ds in ctx.datasets:
        for method in ctx.methods_on(ds):
            for seed in ctx.seeds(ds):
                run = ctx.run_dir(ds, method, seed)
                ev = verify_record(chk, ctx, run, job=f"{ds}/{method}/seed{seed}",
                                   fix=regenerate(ctx, ds, method, seed))
                if ev is not None:
                    chk.evidence[f"{ds}/{method}/seed{seed}"] = ev
    return chk


def verify_record(chk: Check, ctx: AuditContext, run: Path, *, job: str, fix: str) -> dict | None:
    """The result files of one evaluation (``run``: its directory) hash to the content record its job wrote last;
    returns {name: {recorded, found}}, or None when the record cannot be read (a finding recorded).

    Args:
        chk: the check that records the findings; ctx: the audit's context; run: the evaluation's directory;
        job: the evaluation as the findings name it ("dataset/method/seed<seed>"); fix: what to do, in each finding.
    """
    from dswm.protocol.evaluation import EVAL_OUTPUTS, EVAL_RECORD_FILE

    rec_path = run / EVAL_RECORD_FILE
    where = ctx.rel(rec_path)
    try:
        rec = ctx.ledger.read_json(rec_path)
    except FileNotFoundError:
        chk.fail(f"{where}: missing — the evaluate job writes it last, with the SHA-256 of "
                 f"{' and '.join(EVAL_OUTPUTS)}; without it no result file of {job} "
                 f"is proven unchanged since its evaluation; {fix}")
        return None
    except ValueError as exc:
        chk.fail(f"{where}: not valid JSON ({exc}); {fix}")
        return None
    files = rec.get("files") if isinstance(rec, dict) else None
    if not isinstance(files, dict):
        chk.fail(f"{where}: 'files' is {files!r}; expected {{name: {{sha256, bytes}}}} of "
                 f"{list(EVAL_OUTPUTS)}; {fix}")
        return None
    ev: dict = {}
    for name in EVAL_OUTPUTS:
        path = run / name
        entry = files.get(name)
        want = entry.get("sha256") if isinstance(entry, dict) else None
        if not isinstance(want, str) or not want:
            chk.fail(f"{where}: no SHA-256 recorded for {name} (files[{name!r}] = {entry!r}); {fix}")
            continue
        if not path.is_file():
            chk.fail(f"{ctx.rel(path)}: missing, but {where} records SHA-256 {want}; {fix}")
            continue
        found = ctx.ledger.sha256(path)
        if found != want:
            chk.fail(f"{ctx.rel(path)}: SHA-256 is {found}, {where} recorded {want} when the evaluate "
                     f"job wrote it — the result file changed after its evaluation; {fix}")
        ev[name] = {"recorded": want, "found": found}
    return ev
