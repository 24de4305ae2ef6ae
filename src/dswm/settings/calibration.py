"""The demand intensity u: a number of config.yaml, or the calibrate rule's record, read by every job that
simulates (:func:`calibrated_scenario`) and an input of those jobs when u is calibrated (:func:`intensity_inputs`).
"""
from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

from dswm.config import ConfigError
from dswm.settings.model import Settings
from dswm.sim.scenario import CALIBRATE, Scenario

CALIBRATION_RECORD = "results/calibration/demand_intensity.json"
"""What the ``calibrate`` rule writes (relative to the working directory): u and how it was found."""


def read_intensity(record: str | Path) -> float:
    """u from the calibrate rule's record (its key ``demand_intensity``).

    Raises:
        ConfigError: the record is missing or not a JSON object, or its ``demand_intensity`` is missing or not a
            positive finite number; the message names the file and the key.
    """
    path = Path(record)
    try:
        with path.open(encoding="utf-8") as fh:
            data = json.load(fh)
    except FileNotFoundError:
        raise ConfigError(f"{path}: no calibration record (scenario.demand_intensity is {CALIBRATE!r}, so u is read "
                          f"from this file; run the calibrate rule)") from None
    except (OSError, ValueError) as exc:
        raise ConfigError(f"{path}: not a calibration record ({exc}); run the calibrate rule again") from None
    if not isinstance(data, dict) or "demand_intensity" not in data:
        raise ConfigError(f"{path}: missing key 'demand_intensity' (expected the positive u the calibrate rule "
                          f"writes; run it again)")
    u = data["demand_intensity"]
    if isinstance(u, bool) or not isinstance(u, (int, float)) or not math.isfinite(u) or u <= 0:
        raise ConfigError(f"{path}: key 'demand_intensity' must be a positive number; found {u!r} (run the "
                          f"calibrate rule again)")
    return float(u)


def calibrated_scenario(scenario: Scenario, record: str | Path | None) -> Scenario:
    """The scenario a job simulates, hashes and records: ``scenario`` itself when config.yaml holds u, else
    ``scenario`` with u read from the calibrate rule's ``record`` (:func:`read_intensity`).

    Every job that reads u calls this (train, evaluate, select; the audit for its expectations), so they all use
    the one number, and the scenario hash of a result file is the hash of that number.

    Raises:
        ConfigError: u is ``calibrate`` and ``record`` is None, or the record is not valid.
    """
    if not scenario.calibrates:
        return scenario
    if record is None:
        raise ConfigError(f"scenario.demand_intensity is {CALIBRATE!r}, but no calibration record was given (expected "
                          f"{CALIBRATION_RECORD}, the job's input 'intensity')")
    return dataclasses.replace(scenario, demand_intensity=read_intensity(record))


def intensity_inputs(settings: Settings, record: str = CALIBRATION_RECORD) -> dict[str, str]:
    """The extra input of every job that reads u (train, evaluate, select, audit_report).

    Returns:
        ``{"intensity": record}`` when ``scenario.demand_intensity`` is ``calibrate``: the calibrate rule's record is
        then an input, so the rule runs first and a new record reruns the job; ``{}`` when config.yaml holds the
        number (no job depends on the calibrate rule).
    """
    return {"intensity": str(record)} if settings.scenario.calibrates else {}
