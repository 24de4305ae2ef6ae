"""Atomic file writes: write to a temporary file in the target's directory, then os.replace.

A failure anywhere leaves neither the target nor the temporary file behind.
"""
from __future__ import annotations

import contextlib
import json
import os
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any


def _temp_beside(target: Path) -> Path:
    """Creates an empty temporary file in target's directory with the usual (umask) permissions."""
    # The temp name keeps the target's suffix, so writers that infer the format from it behave.
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=f".tmp{target.suffix}", dir=target.parent)
    os.close(fd)
    mask = os.umask(0)
    os.umask(mask)
    os.chmod(tmp, 0o666 & ~mask)
    return Path(tmp)


@contextlib.contextmanager
def atomic_path(target: Path | str) -> Iterator[Path]:
    """Yields a temporary path beside `target`; on success it replaces `target`, on failure it is removed.

    Args:
        target: the final path (its directory is created if needed).
    Yields:
        Path to write to.
    """
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp_path = _temp_beside(target)
    try:
        yield tmp_path
        os.replace(tmp_path, target)
    except BaseException:
        tmp_path.unlink(missing_ok=True)
        raise


@contextlib.contextmanager
def atomic_group(targets: list[Path]) -> Iterator[list[Path]]:
    """Like `atomic_path` for several files that must appear together.

    All temporaries are written first; only when the block succeeds are they moved into place. On failure
    the temporaries are removed and any target that was already moved is removed too.
    """
    targets = [Path(t) for t in targets]
    tmps: list[Path] = []
    for t in targets:
        t.parent.mkdir(parents=True, exist_ok=True)
        tmps.append(_temp_beside(t))
    moved: list[Path] = []
    try:
        yield tmps
        for tmp, t in zip(tmps, targets):
            os.replace(tmp, t)
            moved.append(t)
    except BaseException:
        for p in tmps + moved:
            p.unlink(missing_ok=True)
        raise


def write_json(target: Path | str, obj: Any) -> None:
    """Writes JSON atomically (sorted keys, indented, trailing newline)."""
    with atomic_path(target) as tmp:
        tmp.write_text(json.dumps(obj, indent=2, sort_keys=True) + "\n")


def write_text(target: Path | str, text: str) -> None:
    """Writes a UTF-8 text file atomically."""
    with atomic_path(target) as tmp:
        tmp.write_text(text, encoding="utf-8")


def save_npz(path: str | Path, **arrays) -> None:
    """Write compressed ``.npz`` arrays atomically."""
    import numpy as np

    with atomic_path(path) as tmp, tmp.open("wb") as fh:
        np.savez_compressed(fh, **arrays)


def write_obstacles(paths: Iterable[Path | str]) -> dict[Path, tuple[str, list[Path]]]:
    """What stops files from being written at ``paths`` (the outputs a run is about to write), found before any of
    them is computed: {the existing path in the way: (why, the directories of ``paths`` it stops)}.

    A directory that does not exist yet is judged by its nearest existing ancestor, where it would be created:
    that ancestor must be a directory (a file in the way stops every user, root included) that this user may
    write to and enter.
    """
    out: dict[Path, tuple[str, list[Path]]] = {}
    for directory in sorted({Path(p).parent for p in paths}):
        found = directory
        while not found.exists() and found != found.parent:
            found = found.parent
        if not found.is_dir():
            why = "a file, not a directory"
        elif not os.access(found, os.W_OK | os.X_OK):
            why = "a directory this user may not write to"
        else:
            continue
        out.setdefault(found, (why, []))[1].append(directory)
    return out
