"""Deterministic demo datasets written in each dataset's PUBLISHED raw format.

`generate(name, cfg, out_dir)` writes the raw files that the readers of prep.milan / prep.shanghai /
prep.yjmob then prepare exactly as they would the real ones.
"""
from __future__ import annotations

from pathlib import Path

from prep.config import DatasetConfig


def generate(name: str, cfg: DatasetConfig, out_dir: Path) -> list[Path]:
    """Writes the demo raw files of dataset `name` into `out_dir`.

    Args:
        name: "milan", "shanghai" or "yjmob".
        cfg: that dataset's config (its `demo` section sets seed and sizes).
        out_dir: destination directory.
    Returns:
        Paths of the written raw files.
    """
    if name == "milan":
        from prep.demo.milan import generate as gen
    elif name == "shanghai":
        from prep.demo.shanghai import generate as gen
    elif name == "yjmob":
        from prep.demo.yjmob import generate as gen
    else:
        raise ValueError(f"unknown dataset {name!r}; expected milan, shanghai or yjmob")
    return gen(cfg, Path(out_dir))  # type: ignore[arg-type]
