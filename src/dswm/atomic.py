"""Atomic writers: a file appears complete under its final name or not at all.

Each writer writes a temp file in the destination directory (same file system) and renames it over the
final path with ``os.replace``, so a job killed mid-way never leaves a result file that looks complete.
"""
from __future__ import annotations

import contextlib
import json
import os
from pathlib import Path
from typing import Any, Iterator

import numpy as np


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temp path beside ``path``; on success rename it to ``path``, on error remove it.

    Args:
        path: the final file path (its directory is created).

    Yields:
        The temp path to write to (same suffix as ``path``, so format-sniffing writers behave).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.stem}.tmp{os.getpid()}{path.suffix}")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def write_json(path: str | Path, obj: Any) -> None:
    """Write ``obj`` as indented, key-sorted JSON."""
    with atomic_path(path) as tmp, tmp.open("w") as fh:
        json.dump(obj, fh, indent=2, sort_keys=True)
        fh.write("\n")


def write_text(path: str | Path, text: str) -> None:
    """Write a text file."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def save_npz(path: str | Path, **arrays: np.ndarray) -> None:
    """Write compressed ``.npz`` arrays."""
    with atomic_path(path) as tmp, tmp.open("wb") as fh:
        np.savez_compressed(fh, **arrays)
