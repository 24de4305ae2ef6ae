"""Atomic writers: a file appears complete under its final name or not at all.

The temp-file-then-rename mechanism is ``prep.atomic`` (the lowest layer, shared with data preparation and
the audit); this module adds the array writer the evaluation needs.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from prep.atomic import atomic_group, atomic_path, write_json, write_text

__all__ = ["atomic_group", "atomic_path", "save_npz", "write_json", "write_text"]


def save_npz(path: str | Path, **arrays: np.ndarray) -> None:
    """Write compressed ``.npz`` arrays."""
    with atomic_path(path) as tmp, tmp.open("wb") as fh:
        np.savez_compressed(fh, **arrays)
