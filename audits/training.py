"""Protocol family, part 2: learners learn from training days only and are evaluated with the model they trained.

* `check_training_days`: every learning method's training manifest (its training source's, for a method whose
  training is identical to an earlier one's) records the day of its pre-collected or replayed data, and every
  such day is a training day.
* `check_checkpoints`: the checkpoint and the model file of every train job hash to the SHA-256 the training
  manifest recorded when training ended, and every prepared file training read still hashes to the value
  recorded when it was read (so no checkpoint, model or training input changed once evaluation began reading
  test-day data); training declares that it read no test data. File times are compared only where content is
  unproven: a checkpoint, model or result file whose SHA-256 (for a result, the model_sha256 it records loading)
  equals the recorded one passes whatever its file time; any other checkpoint-like file in the run directory
  must be older than the manifest.
* `check_evaluated_models`: every learning method's result file records the model it evaluated, and that model
  is its training source's model.pt, hashing to the model_sha256 of the source's training manifest.
"""
from __future__ import annotations

import datetime as dt
import shlex
from pathlib import Path

import polars as pl

from audits.context import AuditContext, AuditInputError
from audits.protocol import result_path, result_record
from audits.report import Check

CHECKPOINT_SUFFIXES = (".pt", ".pth", ".ckpt", ".safetensors")
CLOCK_SLACK_S = 1.0
"""checkpoint_written_at is recorded to the second: a file time within 1 s of it is the same write."""
HASH_KEYS = ("checkpoint_sha256", "model_sha256")
"""Content hashes `dswm.pipeline.jobs.train_job` records; a manifest without them predates content hashing."""
MODEL_FILE = "model.pt"
"""The model file of a run directory: the train rule's `model` output, the file the evaluate rule loads."""
EVAL_OUTPUTS = ("days.parquet", "trajectory.npz")


def _manifest(ctx: AuditContext, ds: str, method: str, seed: int) -> tuple[Path, dict]:
    """The training manifest of the train job of `method` (a training source) on (ds, seed)."""
    path = ctx.run_dir(ds, method, seed) / "train_manifest.json"
    try:
        return path, ctx.ledger.read_json(path)
    except FileNotFoundError as exc:
        users = [m for m in ctx.methods if m != method and ctx.learns(m) and ctx.training_source(m) == method]
        also = f" (whose model {', '.join(users)} also evaluate)" if users else ""
        raise AuditInputError(f"{ctx.rel(path)}: training manifest missing for learning method {method}{also}") from exc
    except ValueError as exc:
        raise AuditInputError(f"{ctx.rel(path)}: not valid JSON ({exc})") from exc


def learning_jobs(ctx: AuditContext) -> list[tuple[str, str, int]]:
    """(dataset, method, seed) of every learning method of the profile."""
    return [(ds, m, s) for ds, m, s in ctx.jobs() if ctx.learns(m)]


def training_jobs(ctx: AuditContext) -> dict[tuple[str, str, int], list[str]]:
    """{(dataset, training source, seed): the learning methods that evaluate its model} of every train job."""
    out: dict[tuple[str, str, int], list[str]] = {}
    for ds, method, seed in learning_jobs(ctx):
        out.setdefault((ds, ctx.training_source(method), seed), []).append(method)
    return out


def check_training_days(ctx: AuditContext) -> Check:
    """Every learning method records the day of its training data, and all of them are training days."""
    chk = Check(id="protocol.training_days", family="protocol",
                claim="Every learning method's training manifest (that of its training source, for a method whose "
                      "training is identical to an earlier one's) records the tensor day of every pre-collected "
                      "or replayed transition, and every one of them is a training day.")
    learners = learning_jobs(ctx)
    chk.evidence["learning_jobs"] = ({f"{d}/{m}/seed{s}": ctx.rel(ctx.run_dir(d, ctx.training_source(m), s) /
                                                                  "train_manifest.json") for d, m, s in learners} or
                                     "none: no method of methods.run learns, nothing to verify")
    for (ds, method, seed), users in training_jobs(ctx).items():
        try:
            path, man = _manifest(ctx, ds, method, seed)
            train = set(ctx.train_index(ds).tolist())
            days = manifest_days(chk, ctx, ds, man, where=ctx.rel(path), method=method)
        except AuditInputError as exc:
            chk.fail(str(exc))
            continue
        if days is None:
            continue
        n = man.get("n_transitions")
        chk.evidence[f"{ds}/{method}/seed{seed}"] = {"records": len(days), "distinct_days": len(set(days)),
                                                     "training_days_covered": f"{len(set(days) & train)}/{len(train)}",
                                                     "n_transitions": n, "evaluated_by": users}
    return chk


def manifest_days(chk: Check, ctx: AuditContext, ds: str, man: dict, *, where: str, method: str) -> list[int] | None:
    """The tensor days a training manifest records (its ``days``), each checked to be a training day, with its
    ``day_labels`` and transition count checked against them; None (a finding recorded) when it records none.

    Args:
        chk: the check that records the findings; ctx: the audit's context (its settings say which days train);
        ds: the manifest's dataset; man: the manifest; where: its path as the findings name it; method: the method
        it trained.
    Raises:
        AuditInputError: meta.json of ``ds`` cannot be read.
    """
    labels = {d["index"]: d["label"] for d in ctx.meta(ds)["days"]}
    train = set(ctx.train_index(ds).tolist())
    days = man.get("days")
    if not isinstance(days, list) or not days:
        chk.fail(f"{where}: 'days' is {days!r}; expected the tensor day of every transition or sequence used")
        return None
    days = [int(d) for d in days]
    leaked = sorted(set(d for d in days if d not in train))
    if leaked:
        chk.fail(f"{where}: training data holds day(s) {[labels.get(d, d) for d in leaked]} (indices {leaked}) "
                 f"that are not training days — the replay/pre-collected data of {method} holds "
                 f"{'a test day' if all(d in labels for d in leaked) else 'unknown days'}")
    if "day_labels" in man and [labels.get(d) for d in days] != list(man["day_labels"]):
        chk.fail(f"{where}: day_labels disagree with the labels meta.json gives the recorded day indices")
    per = man.get("transitions_per_day_episode")
    n = man.get("n_transitions")
    if per is not None and n is not None and int(n) != int(per) * len(days):
        chk.fail(f"{where}: n_transitions = {n}, but {len(days)} recorded day episodes x {per} = "
                 f"{int(per) * len(days)} — some transitions have no recorded day")
    if per is None and n is not None and int(n) != len(days):
        chk.fail(f"{where}: n_transitions = {n}, but {len(days)} days are recorded (one per transition "
                 f"expected)")
    return days


def declares_no_test_data(chk: Check, man: dict, where: str) -> None:
    """The training manifest ``man`` (at ``where``) records ``read_test_data: false``; a finding otherwise."""
    if "read_test_data" not in man:
        chk.fail(f"{where}: read_test_data is not recorded; expected false (training reads no test-day data)")
    elif man["read_test_data"] is not False:
        chk.fail(f"{where}: read_test_data = {man['read_test_data']!r}; expected false — training read "
                 f"test-day data")


def _parse_utc(text: str) -> float:
    return dt.datetime.strptime(text, "%Y-%m-%dT%H:%M:%SZ").replace(tzinfo=dt.timezone.utc).timestamp()


def _under_root(ctx: AuditContext, recorded) -> Path:
    """A path a manifest records (relative to the workflow's working directory, or absolute)."""
    p = Path(str(recorded))
    return p if p.is_absolute() else ctx.root / p


def _same_hash(chk: Check, ctx: AuditContext, path: Path, recorded, *, where: str, key: str, leak: str) -> dict:
    """Compares the SHA-256 of `path` now with the value `where` records under `key`; returns the evidence.

    Nothing is compared when no value is recorded (check_checkpoints reports the missing key once).
    """
    found = ctx.ledger.sha256(path)
    if recorded and found != recorded:
        chk.fail(f"{ctx.rel(path)}: SHA-256 is {found}, {where} recorded {key} = {recorded} — {leak}")
    return {"recorded": recorded, "found": found}


def _proven(ctx: AuditContext, path: Path, recorded) -> bool:
    """True when `path` hashes to the SHA-256 a manifest recorded for it: its content is the one recorded when
    training ended, so its file time proves nothing more (a touch or a copy without times changes only that)."""
    return bool(recorded) and path.is_file() and ctx.ledger.sha256(path) == recorded


def _loaded_sha256(ctx: AuditContext, result: Path) -> str | None:
    """The model_sha256 a result file records the evaluation loaded (None when it records none or is unreadable;
    check_evaluated_models reports that)."""
    from dswm.protocol.evaluation import read_model_record

    try:
        rec = read_model_record(ctx.ledger.track(result))
    except (OSError, ValueError, pl.exceptions.PolarsError):
        return None
    return rec.get("model_sha256") if rec else None


def _checkpoint(chk: Check, ctx: AuditContext, man: dict, where: str) -> dict:
    """The recorded checkpoint exists and hashes to checkpoint_sha256; where no such hash is recorded, or it
    differs, its file time is the recorded write time."""
    ck = man.get("checkpoint")
    if not ck:
        chk.fail(f"{where}: no checkpoint recorded")
        return {}
    cpath = _under_root(ctx, ck)
    if not cpath.is_file():
        chk.fail(f"{where}: recorded checkpoint {ck} does not exist")
        return {}
    written = cpath.stat().st_mtime
    ev = {"checkpoint_sha256": _same_hash(chk, ctx, cpath, man.get("checkpoint_sha256"), where=where,
                                          key="checkpoint_sha256",
                                          leak="the checkpoint was rewritten after training ended"),
          "checkpoint_mtime": written}
    rec = man.get("checkpoint_written_at")
    try:
        rec_t = _parse_utc(str(rec))
    except ValueError:
        chk.fail(f"{where}: checkpoint_written_at = {rec!r}; expected YYYY-MM-DDTHH:MM:SSZ")
        return ev
    if _proven(ctx, cpath, man.get("checkpoint_sha256")):
        ev["checkpoint_time"] = "not compared: the content hashes to checkpoint_sha256"
    elif not rec_t - CLOCK_SLACK_S <= written < rec_t + 1 + CLOCK_SLACK_S:
        chk.fail(f"{ctx.rel(cpath)}: modified at {_iso(written)}, the manifest recorded {rec} — the "
                 f"checkpoint was rewritten after training ended")
    return ev


def _model(chk: Check, ctx: AuditContext, man: dict, where: str, run: Path) -> dict:
    """The manifest names the run's model.pt, which hashes to model_sha256."""
    mpath = run / MODEL_FILE
    rec = man.get("model")
    if rec and _under_root(ctx, rec).resolve() != mpath.resolve():
        chk.fail(f"{where}: model = {rec!r}; expected {ctx.rel(mpath)}, the file the evaluation loads")
    if not mpath.is_file():
        chk.fail(f"{ctx.rel(mpath)}: missing; the evaluation of a learning method loads it")
        return {}
    return {"model_sha256": _same_hash(chk, ctx, mpath, man.get("model_sha256"), where=where, key="model_sha256",
                                       leak="the model file was rewritten after training ended")}


def _data_files(chk: Check, ctx: AuditContext, man: dict, where: str, ds: str) -> dict:
    """data_files_read lists {path, sha256} of the dataset's prepared files, each unchanged since training."""
    entries = man.get("data_files_read")
    if (not isinstance(entries, list) or not entries or
            not all(isinstance(e, dict) and {"path", "sha256"} <= set(e) for e in entries)):
        chk.fail(f"{where}: data_files_read = {entries!r}; expected a list of {{path, sha256}} of the prepared "
                 f"files training read — the manifest predates content hashing; re-run the train job")
        return {}
    ev = {}
    for e in entries:
        path = _under_root(ctx, e["path"])
        if path.name in EVAL_OUTPUTS:
            chk.fail(f"{where}: training read evaluation output {e['path']}")
        if not path.is_file():
            chk.fail(f"{where}: data_files_read names {e['path']}, which does not exist; expected the file "
                     f"training read, unchanged")
            continue
        ev[ctx.rel(path)] = _same_hash(chk, ctx, path, e["sha256"], where=where,
                                       key=f"data_files_read[{e['path']!r}].sha256",
                                       leak="a training input changed after training")
    read = {_under_root(ctx, e["path"]).resolve() for e in entries}
    for need in (ctx.tensor_path(ds), ctx.meta_path(ds)):
        if need.resolve() not in read:
            chk.fail(f"{where}: data_files_read lacks {ctx.rel(need)}; expected the prepared files of {ds} "
                     f"the train job loads")
    return ev


def check_checkpoints(ctx: AuditContext) -> Check:
    """Checkpoint, model and training inputs unchanged since training; training declares no test data read."""
    chk = Check(id="protocol.checkpoints", family="protocol",
                tolerance=f"contents: SHA-256 equal; file times (compared only where no recorded hash proves the "
                          f"content) within {CLOCK_SLACK_S:g} s (checkpoint_written_at is recorded to the second)",
                claim="Every train job's checkpoint and model file hash to the SHA-256 its training manifest "
                      "recorded when training ended, and the prepared tensor and meta.json it read hash to the "
                      "values recorded when it read them, so none changed once evaluation began reading test-day "
                      "data; no checkpoint file whose content is unproven (no recorded hash, or another one) is "
                      "newer than the manifest; no result file that evaluates the model and does not record "
                      "loading model_sha256 is older than it; training declares it read no test data.")
    for (ds, method, seed), users in training_jobs(ctx).items():
        try:
            mpath, man = _manifest(ctx, ds, method, seed)
        except AuditInputError as exc:
            chk.fail(str(exc))
            continue
        where, run = ctx.rel(mpath), ctx.run_dir(ds, method, seed)
        declares_no_test_data(chk, man, where)
        missing = [k for k in HASH_KEYS if not man.get(k)]
        if missing:
            chk.fail(f"{where}: no {' or '.join(missing)} recorded — the manifest predates content hashing; "
                     f"re-run the train job of {ds}/{method}/seed{seed}")
        closed = mpath.stat().st_mtime
        ev: dict = {"manifest_closed": closed, **_checkpoint(chk, ctx, man, where), **_model(chk, ctx, man, where, run),
                    "data_files_read": _data_files(chk, ctx, man, where, ds)}
        # File times speak only where content is unproven: the recorded checkpoint and the model file that hash to
        # the values the manifest recorded, and a result that records loading the model of model_sha256, are the
        # files training and evaluation ended with, whenever their file times say they were written.
        recorded = {(run / MODEL_FILE).resolve(): man.get("model_sha256")}
        if man.get("checkpoint"):
            recorded[_under_root(ctx, man["checkpoint"]).resolve()] = man.get("checkpoint_sha256")
        proven_by_hash = []
        for f in sorted(run.rglob("*")) if run.is_dir() else []:
            if f.is_file() and f.suffix in CHECKPOINT_SUFFIXES and f.stat().st_mtime > closed + CLOCK_SLACK_S:
                if _proven(ctx, f, recorded.get(f.resolve())):
                    proven_by_hash.append(ctx.rel(f))
                    continue
                chk.fail(f"{ctx.rel(f)}: written at {_iso(f.stat().st_mtime)}, after the training manifest closed "
                         f"at {_iso(closed)} — a checkpoint written after reading test-day data")
        for user in users:
            result = result_path(ctx, ds, user, seed)
            if result.is_file() and result.stat().st_mtime + CLOCK_SLACK_S < closed:
                if man.get("model_sha256") and _loaded_sha256(ctx, result) == man["model_sha256"]:
                    proven_by_hash.append(ctx.rel(result))
                    continue
                chk.fail(f"{ctx.rel(result)}: written before its training manifest {where} closed — the "
                         f"evaluation did not use the final checkpoint")
        if proven_by_hash:
            ev["file_times_not_compared"] = proven_by_hash
        chk.evidence[f"{ds}/{method}/seed{seed}"] = {**ev, "evaluated_by": users}
    return chk


def check_evaluated_models(ctx: AuditContext) -> Check:
    """Every learning evaluation loaded its training source's model, the one that source's manifest records."""
    from dswm.protocol.evaluation import MODEL_RECORD_KEY, read_model_record

    chk = Check(id="protocol.evaluated_models", family="protocol",
                claim="Every learning method's result file records the model it evaluated: the model.pt of its "
                      "training source (the first method of methods.run whose training is identical; the method "
                      "itself otherwise) and that source's training manifest; the SHA-256 taken when the "
                      "evaluation loaded it and the SHA-256 of the file now both equal the manifest's model_sha256.")
    for ds, method, seed in learning_jobs(ctx):
        source = ctx.training_source(method)
        days = result_path(ctx, ds, method, seed)
        where = ctx.rel(days)
        want_model = ctx.run_dir(ds, source, seed) / MODEL_FILE
        want_manifest = ctx.run_dir(ds, source, seed) / "train_manifest.json"
        rec = result_record(ctx, chk, days, read=read_model_record, key=MODEL_RECORD_KEY,
                            holds="the model file the evaluation loaded, its SHA-256 and its training source",
                            job=f"{ds}/{method}/seed{seed}")
        if rec is None:
            continue
        if rec.get("train_source") != source:
            chk.fail(f"{where}: train_source = {rec.get('train_source')!r}, expected {source!r} (the training "
                     f"source config.yaml gives {method})")
        claimed = rec.get("train_manifest")
        if not claimed or _under_root(ctx, claimed).resolve() != want_manifest.resolve():
            chk.fail(f"{where}: train_manifest = {claimed!r}, expected {ctx.rel(want_manifest)}")
        if not rec.get("model"):
            chk.fail(f"{where}: model = {rec.get('model')!r}, expected {ctx.rel(want_model)}, the model {source} "
                     f"trained")
            continue
        mpath = _under_root(ctx, rec["model"])
        if mpath.resolve() != want_model.resolve():
            chk.fail(f"{where}: model = {rec['model']!r}, expected {ctx.rel(want_model)}, the model {source} trained")
        try:
            _, man = _manifest(ctx, ds, source, seed)
        except AuditInputError as exc:
            chk.fail(str(exc))
            continue
        hashes = verify_loaded_model(chk, ctx, where=where, rec=rec, mpath=mpath, want_model=want_model,
                                     manifest=want_manifest, man=man, method=method, source=source,
                                     train_job=f"{ds}/{source}/seed{seed}")
        if hashes is None:
            continue
        expected, loaded, found = hashes
        chk.evidence[f"{ds}/{method}/seed{seed}"] = {"train_source": source, "model": ctx.rel(mpath),
                                                     "expected": expected, "loaded": loaded, "found": found}
    return chk


def verify_loaded_model(chk: Check, ctx: AuditContext, *, where: str, rec: dict, mpath: Path, want_model: Path,
                        manifest: Path, man: dict, method: str, source: str,
                        train_job: str) -> tuple[str, str | None, str | None] | None:
    """An evaluation loaded the model its training source trained: the SHA-256 it recorded at load time and the
    model file's SHA-256 now both equal the manifest's model_sha256.

    Args:
        chk: the check that records the findings; ctx: the audit's context; where: the result file, as named;
        rec: its model record; mpath: the model file it records; want_model: the source's model file;
        manifest, man: the source's training manifest (path and content); method, source: the evaluated method and
        its training source; train_job: the train job that writes the model ("dataset/[variant/]method/seed<seed>").
    Returns:
        (expected, loaded, found) SHA-256s, or None when the manifest records no model_sha256 (a finding).
    """
    expected = man.get("model_sha256")
    if not expected:
        chk.fail(f"{ctx.rel(manifest)}: no model_sha256 recorded — the manifest predates content hashing; "
                 f"re-run the train job of {train_job}")
        return None
    loaded = rec.get("model_sha256")
    if loaded != expected:
        chk.fail(f"{where}: the evaluation loaded {ctx.rel(mpath)} with SHA-256 {loaded}, expected {expected} "
                 f"(model_sha256 of {ctx.rel(manifest)}) — {method} was evaluated with a model {source} "
                 f"did not train")
    found = ctx.ledger.sha256(mpath) if mpath.is_file() else None
    if found is None:
        chk.fail(f"{ctx.rel(mpath)}: missing; {where} records it as the model it evaluated")
    elif found != expected:
        # The source's own model truncated or replaced: its train job writes it again.
        rel = shlex.quote(ctx.rel(mpath))
        fix = (f"; re-run its train job: `rm {rel}`, then the same snakemake command again (or add "
               f"`--forcerun {rel}` to it)" if mpath.resolve() == want_model.resolve() else "")
        chk.fail(f"{ctx.rel(mpath)}: SHA-256 is {found}, expected {expected} (model_sha256 of "
                 f"{ctx.rel(manifest)}, which {where} names) — not the model {source} trained{fix}")
    return expected, loaded, found


def _iso(t: float) -> str:
    return dt.datetime.fromtimestamp(t, dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%S.%fZ")
