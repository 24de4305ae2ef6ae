"""Model snapshots taken while a training run crosses fixed fractions of its budget: the checkpoints of the
sample-efficiency probe (paper Section V-E, Fig. sample; config.yaml ``figures.sample_efficiency``).

A train job of (``figures.dataset``, a method of ``figures.sample_efficiency.methods``, a seed of ``figures.seeds``)
builds a :class:`Snapshots` (:func:`for_train_job`) and passes it to its controller's ``fit(..., snapshots=)``.
The fit loop calls :meth:`Snapshots.claim` with its checkpoint before it looks at it, and :meth:`Snapshots.step`
after every unit of its budget (a round, a day-episode, a gradient step, a task), before any checkpoint of that
unit. A fraction f is due at the first unit ``done`` with ``done / total >= f``; the model file written then is
what the controller's ``save`` writes at that point (a loadable model, the probe's input). A run that asks for the
untrained point as well (``untrained``: the learning curves, ``dswm.pipeline.learning``) has its fit loop call
:meth:`Snapshots.start` once the model is built, before its first update: fraction 0, the model as initialised.
Each snapshot records the environment transitions and the gradient steps done by then. Taking a snapshot reads
the training state and changes none of it, so a run trains the same model with and without snapshots.

Snapshots live in the job's run directory (``<run_dir>/snapshots/``, beside the checkpoint, kept across an
interrupted job) with a journal of those taken. A run resumes its checkpoint only when the journal was written under
the same key (the job's settings, fractions and inputs): every snapshot before the checkpoint is then in the
journal. Otherwise :meth:`Snapshots.claim` removes the checkpoint and training starts afresh. At the end
:func:`export` links them into the train rule's ``snapshots`` output with ``index.json`` (:data:`INDEX_FILE`).
"""
from __future__ import annotations

import json
import math
import os
import shutil
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

from dswm.config import stable_hash
from prep.atomic import atomic_path, write_json
from prep.rawio import sha256_file

INDEX_FILE = "index.json"
"""The snapshot index in a train job's ``snapshots`` output: {"method", "seed", "fractions", "snapshots": [{"fraction",
"done", "total", "fraction_done", "n_transitions", "gradient_steps", "file", "sha256"}]}, one entry per requested
fraction (fraction 0 first when the untrained model was asked for; ``gradient_steps`` null where the fit loop does
not count them)."""
JOURNAL_FILE = "journal.json"
"""The record of the snapshots taken so far in ``<run_dir>/snapshots/``: {"key", "fractions", "taken": [...]}."""
STORE = "snapshots"
"""The directory of the snapshots under a train job's run directory."""


class SnapshotError(RuntimeError):
    """A snapshot is missing, or its file differs from the hash recorded when it was taken; the message names it."""


def check_fractions(fractions: Sequence[float],
                    where: str = "figures.sample_efficiency.fractions") -> tuple[float, ...]:
    """``fractions`` as a sorted tuple of distinct numbers in (0, 1].

    Raises:
        ValueError: a fraction outside (0, 1], a repeated one, or none at all (the message names ``where``).
    """
    out = tuple(sorted(float(f) for f in fractions))
    if not out or any(not 0.0 < f <= 1.0 for f in out) or len(set(out)) != len(out):
        raise ValueError(f"config key {where}: expected distinct fractions of the training budget in (0, 1], "
                         f"found {list(fractions)}")
    return out


def due_unit(fraction: float, total: int) -> int:
    """The unit (1-based) at which ``fraction`` of a budget of ``total`` units is reached: ceil(fraction x total)."""
    return max(1, math.ceil(fraction * total - 1e-9))


class Snapshots:
    """The snapshots of one training run.

    Args:
        fractions: the budget fractions to snapshot (:func:`check_fractions`).
        store: the directory of the snapshot files and the journal (``<run_dir>/snapshots``).
        key: what the run's snapshots depend on (:func:`job_key`); a journal under another key is not continued.
        untrained: also snapshot the model before its first update (fraction 0, :meth:`start`).
    """

    def __init__(self, *, fractions: Sequence[float], store: str | Path, key: str, untrained: bool = False):
        self.fractions = check_fractions(fractions)
        self.untrained = bool(untrained)
        self.store = Path(store)
        self.key = key
        self.taken: dict[float, dict] = {}
        journal = self._read_journal()
        self.matches = (journal is not None and journal.get("key") == key
                        and [float(f) for f in journal.get("fractions", [])] == list(self.fractions))
        if self.matches:
            self.taken = {float(e["fraction"]): dict(e) for e in journal.get("taken", [])}

    def _read_journal(self) -> dict | None:
        path = self.store / JOURNAL_FILE
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return None
        return data if isinstance(data, dict) else None

    def _write_journal(self) -> None:
        write_json(self.store / JOURNAL_FILE, {"key": self.key, "fractions": list(self.fractions),
                                               "taken": [self.taken[f] for f in sorted(self.taken)]})

    def claim(self, checkpoint: str | Path) -> None:
        """Call before ``fit`` reads ``checkpoint``: when the journal was not written under this run's key (no
        snapshots, other fractions, other settings or inputs), the checkpoint cannot show which snapshots its run
        took, so it is removed (training starts afresh) and the store is emptied; then the journal names this key.
        """
        if self.matches:
            return
        Path(checkpoint).unlink(missing_ok=True)
        if self.store.is_dir():
            shutil.rmtree(self.store)
        self.store.mkdir(parents=True, exist_ok=True)
        self.taken = {}
        self._write_journal()
        self.matches = True

    def requested(self) -> tuple[float, ...]:
        """Every fraction this run snapshots, in order: 0 first when :attr:`untrained`."""
        return ((0.0,) if self.untrained else ()) + self.fractions

    def start(self, *, total: int, n_transitions: int, write: Callable[[Path], None],
              gradient_steps: int | None = 0) -> list[float]:
        """Once the model is built, before its first update: the untrained snapshot (fraction 0), when asked for
        and not yet taken (a resumed run took it before its checkpoint).

        Args:
            total: units of the budget in all.
            n_transitions: environment transitions consumed so far (pre-collected ones included).
            write: writes the model file at the given path (the controller's ``save`` of the initial model).
            gradient_steps: gradient steps done so far (0 before the first update).
        Returns:
            [0.0] when taken now, else [].
        """
        if not self.untrained or 0.0 in self.taken:
            return []
        return self._take([0.0], done=0, total=total, n_transitions=n_transitions, gradient_steps=gradient_steps,
                          write=write, name=f"snapshot_untrained_of{total}.pt")

    def due(self, done: int, total: int) -> list[float]:
        """The fractions due at unit ``done`` of ``total``: those whose :func:`due_unit` is ``done``."""
        return [f for f in self.fractions if due_unit(f, total) == done]

    def step(self, *, done: int, total: int, n_transitions: int, write: Callable[[Path], None],
             gradient_steps: int | None = None) -> list[float]:
        """After unit ``done`` of ``total``: take the snapshot of every fraction due now.

        Args:
            done, total: units of the budget done and in all.
            n_transitions: environment transitions consumed so far (pre-collected ones included).
            write: writes the model file at the given path (the controller's ``save`` of the current state).
            gradient_steps: gradient steps done so far (None: the fit loop does not count them).
        Returns:
            The fractions taken (empty when none is due).
        """
        due = self.due(done, total)
        if not due:
            return []
        return self._take(due, done=done, total=total, n_transitions=n_transitions, gradient_steps=gradient_steps,
                          write=write, name=f"snapshot_{done:0{len(str(total))}d}of{total}.pt")

    def _take(self, fractions: list[float], *, done: int, total: int, n_transitions: int,
              gradient_steps: int | None, write: Callable[[Path], None], name: str) -> list[float]:
        """Write one snapshot file ``name`` for ``fractions`` and record it in the journal."""
        if not self.matches:
            raise SnapshotError(f"{self.store}: a snapshot before claim(); the fit loop must claim its "
                                f"checkpoint first")
        self.store.mkdir(parents=True, exist_ok=True)
        write(self.store / name)
        digest = sha256_file(self.store / name)
        for f in fractions:
            self.taken[f] = {"fraction": f, "done": int(done), "total": int(total), "fraction_done": done / total,
                             "n_transitions": int(n_transitions),
                             "gradient_steps": None if gradient_steps is None else int(gradient_steps),
                             "file": name, "sha256": digest}
        self._write_journal()
        return fractions

    def entries(self) -> list[dict]:
        """One entry per fraction, in order, each file checked against its hash.

        Raises:
            SnapshotError: a fraction was never taken, or its file is missing or changed.
        """
        out = []
        for f in self.requested():
            e = self.taken.get(f)
            if e is None:
                raise SnapshotError(f"{self.store / JOURNAL_FILE}: no snapshot at fraction {f} of the budget (taken: "
                                    f"{sorted(self.taken)}); delete {self.store.parent} and run the train job again")
            path = self.store / e["file"]
            if not path.is_file() or sha256_file(path) != e["sha256"]:
                raise SnapshotError(f"{path}: missing or not the snapshot recorded at fraction {f} (SHA-256 "
                                    f"{e['sha256']}); delete {self.store.parent} and run the train job again")
            out.append(e)
        return out


def job_key(*, job: Mapping[str, Any], method: str, seed: int, data_files: Sequence[Mapping[str, str]]) -> str:
    """The key of a train job's snapshots: its settings slice (fractions included), method, seed and the SHA-256
    of every prepared file it reads."""
    return stable_hash({"job": job, "method": method, "seed": int(seed),
                        "data": [[d["path"], d["sha256"]] for d in data_files]})


def for_train_job(*, job: Mapping[str, Any], method: str, seed: int, run_dir: str | Path,
                  data_files: Sequence[Mapping[str, str]]) -> Snapshots | None:
    """The :class:`Snapshots` a train job passes to ``fit``: None unless its slice holds ``snapshots.fractions``
    (``dswm.settings.train_slice`` adds it for the probed jobs only; the learning runs' slice with ``untrained``:
    true)."""
    spec = job.get("snapshots")
    if not spec:
        return None
    return Snapshots(fractions=spec["fractions"], store=Path(run_dir) / STORE, untrained=bool(spec.get("untrained")),
                     key=job_key(job=job, method=method, seed=seed, data_files=data_files))


def export(snapshots: Snapshots | None, out_dir: str | Path, *, method: str, seed: int) -> dict | None:
    """Create the train rule's ``snapshots`` output ``out_dir``: empty when ``snapshots`` is None, else every
    snapshot file (a hard link to the one in the store, a copy where links are not possible: the store's files are
    replaced, never rewritten in place) and :data:`INDEX_FILE`, written last.

    Returns:
        The index written, or None.

    Raises:
        SnapshotError: a fraction was not taken (:meth:`Snapshots.entries`).
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if snapshots is None:
        return None
    entries = snapshots.entries()
    for name in dict.fromkeys(e["file"] for e in entries):
        with atomic_path(out_dir / name) as tmp:
            tmp.unlink()
            try:
                os.link(snapshots.store / name, tmp)
            except OSError:
                shutil.copyfile(snapshots.store / name, tmp)
        if sha256_file(out_dir / name) != next(e["sha256"] for e in entries if e["file"] == name):
            raise SnapshotError(f"{out_dir / name}: the copy does not hash to the snapshot taken")
    index = {"method": method, "seed": int(seed), "fractions": list(snapshots.requested()), "snapshots": entries}
    write_json(out_dir / INDEX_FILE, index)
    return index


def read_index(out_dir: str | Path) -> list[dict]:
    """The entries of a train job's snapshot index, each with ``path`` (the file under ``out_dir``) added and its
    SHA-256 checked.

    Raises:
        SnapshotError: no index, or a file missing or changed since the train job wrote it.
    """
    out_dir = Path(out_dir)
    try:
        index = json.loads((out_dir / INDEX_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise SnapshotError(f"{out_dir / INDEX_FILE}: cannot read the snapshot index ({exc}); expected the train "
                            f"job of a probed (dataset, method, seed) to write it (figures.sample_efficiency)") from exc
    out = []
    for e in index.get("snapshots", []):
        path = out_dir / e["file"]
        if not path.is_file() or sha256_file(path) != e["sha256"]:
            raise SnapshotError(f"{path}: missing or changed since its train job recorded SHA-256 {e['sha256']} "
                                f"in {out_dir / INDEX_FILE}; run the train job again")
        out.append({**e, "path": str(path)})
    if not out:
        raise SnapshotError(f"{out_dir / INDEX_FILE}: lists no snapshot")
    return out
