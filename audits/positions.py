"""Readers of the records the pipeline keeps of derived quantities: initial positions and calibration.

* Initial positions: every result directory's `trajectory.npz` holds the fleet positions per slot of the
  days it traces; slot 0 of every traced day is the initial deployment p_0 (identical for every method).
* Calibration: the record the `calibrate` rule writes (results/calibration/demand_intensity.json).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from audits.context import AuditContext, AuditInputError

CALIBRATION_RECORD = "demand_intensity.json"


def _slot0_arrays(arrays: dict[str, np.ndarray], k: int, slots: int) -> dict[str, np.ndarray]:
    """{key[/day]: (K, 2)} initial positions found in a trajectory file's arrays."""
    out = {}
    for key, arr in arrays.items():
        if arr.ndim >= 3 and arr.shape[-2:] == (k, 2) and arr.shape[-3] in (slots, slots + 1):
            first = arr[..., 0, :, :].reshape(-1, k, 2)
            for i, pos in enumerate(first):
                out[f"{key}[{i}]" if len(first) > 1 else key] = pos.astype(np.float64)
        elif key in ("init_pos", "initial_positions") and arr.shape == (k, 2):
            out[key] = arr.astype(np.float64)
    return out


def recorded_initial_positions(ctx: AuditContext, ds: str) -> dict[str, np.ndarray]:
    """{"<file>:<array>": (K, 2)} initial positions recorded by every job of `ds`.

    Raises:
        AuditInputError: no job of the dataset recorded its positions.
    """
    k, slots = ctx.scenario.n_uavs, ctx.scenario.slots_per_day
    found: dict[str, np.ndarray] = {}
    for method in ctx.methods_on(ds):
        for seed in ctx.seeds(ds):
            path = ctx.run_dir(ds, method, seed) / "trajectory.npz"
            if not path.is_file():
                continue
            with np.load(ctx.ledger.track(path), allow_pickle=False) as z:
                arrays = {name: z[name] for name in z.files}
            for key, pos in _slot0_arrays(arrays, k, slots).items():
                found[f"{ctx.rel(path)}:{key}"] = pos
    if not found:
        raise AuditInputError(f"results/{ds}/*/seed*/trajectory.npz: no fleet positions per slot recorded")
    return found


def calibration_record(ctx: AuditContext) -> tuple[str, dict]:
    """(path relative to the root, content) of the calibration record.

    Raises:
        FileNotFoundError: the calibrate rule has not run (its record is optional when config.yaml holds u).
        AuditInputError: the record is not valid JSON.
    """
    path: Path = ctx.results / "calibration" / CALIBRATION_RECORD
    if not path.is_file():
        raise FileNotFoundError(f"{ctx.rel(path)}: no calibration record (the calibrate rule has not run)")
    try:
        return ctx.rel(path), ctx.ledger.read_json(path)
    except ValueError as exc:
        raise AuditInputError(f"{ctx.rel(path)}: not valid JSON ({exc})") from exc
