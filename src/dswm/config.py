"""Typed scenario configuration built from the ``scenario`` section of ``config.yaml``.

Every constant of SPEC section 1 lives in one frozen dataclass tree. ``Scenario.from_dict`` refuses unknown
or missing keys and values of the wrong type with a message that names the key, so a typo never silently
falls back to a default.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from pathlib import Path
from typing import Any, Mapping

import yaml


class ConfigError(ValueError):
    """A configuration value is missing, unknown or of the wrong form."""


def stable_hash(obj: Any, *, length: int = 16) -> str:
    """Hash of a JSON-serialisable object that does not depend on key order.

    Args:
        obj: nested dicts/lists of numbers, strings, booleans and None (dataclasses are converted).
        length: number of hex digits kept.

    Returns:
        A hex digest prefix, identical across runs and machines for equal inputs.
    """
    if dataclasses.is_dataclass(obj):
        obj = dataclasses.asdict(obj)
    text = json.dumps(obj, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:length]


def _build(cls, data: Mapping[str, Any], where: str):
    """Build dataclass ``cls`` from ``data``, checking keys and scalar types; ``where`` names the section."""
    if not isinstance(data, Mapping):
        raise ConfigError(f"{where}: expected a mapping, found {type(data).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {unknown}; expected keys are {sorted(fields)}")
    missing = sorted(set(fields) - set(data))
    if missing:
        raise ConfigError(f"{where}: missing key(s) {missing}")
    kwargs = {}
    for name, f in fields.items():
        value = data[name]
        sub = _SUBSECTIONS.get((cls.__name__, name))
        key = f"{where}.{name}"
        if sub is not None:
            kwargs[name] = _build(sub, value, key)
            continue
        expected = f.type if isinstance(f.type, str) else f.type.__name__
        if expected == "int":
            if isinstance(value, bool) or not isinstance(value, int):
                raise ConfigError(f"{key}: expected an integer, found {value!r}")
        elif expected == "float":
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ConfigError(f"{key}: expected a finite number, found {value!r}")
            value = float(value)
        kwargs[name] = value
    return cls(**kwargs)


@dataclasses.dataclass(frozen=True, kw_only=True)
class Channel:
    """Al-Hourani air-to-ground channel (urban)."""

    a: float
    """Sigmoid constant a of the LoS probability."""
    b: float
    """Sigmoid constant b of the LoS probability (per degree)."""
    eta_los_db: float
    """Excess path loss of the LoS component, dB."""
    eta_nlos_db: float
    """Excess path loss of the NLoS component, dB."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class Rotor:
    """Rotary-wing power model constants (Zeng, Xu, Zhang 2019)."""

    weight_n: float
    air_density: float
    rotor_radius_m: float
    disc_area_m2: float
    blade_angular_velocity: float
    tip_speed_mps: float
    rotor_solidity: float
    fuselage_drag_ratio: float
    induced_power_correction: float
    profile_drag_coefficient: float


@dataclasses.dataclass(frozen=True, kw_only=True)
class InitConfig:
    """Initial state of every evaluated day."""

    kmeans_seed: int
    """Seed of the demand-weighted K-means of the mean training map."""
    battery_low_frac: float
    """Lowest initial battery, fraction of E_batt."""
    battery_high_frac: float
    """Highest initial battery, fraction of E_batt."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class Scenario:
    """All scenario constants of SPEC section 1."""

    n_uavs: int
    altitude_m: float
    slot_s: float
    slots_per_day: int
    d_max_m: float
    v_max_mps: float
    carrier_hz: float
    bandwidth_hz: float
    tx_power_w: float
    noise_psd_log10_w_per_hz: float
    r0_bps: float
    u_peak: float
    demand_intensity: float
    battery_j: float
    reserve_frac: float
    recharge_slots: int
    n_stations: int
    reward_alpha: float
    reward_beta: float
    obs_window: int
    channel: Channel
    rotor: Rotor
    init: InitConfig

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], *, where: str = "scenario") -> "Scenario":
        """Build from the ``scenario`` mapping of config.yaml; raises ConfigError naming the bad key."""
        scenario = _build(cls, data, where)
        checks = [
            ("n_uavs", scenario.n_uavs >= 1, "at least 1"),
            ("slots_per_day", scenario.slots_per_day > scenario.obs_window, "more than obs_window"),
            ("reserve_frac", 0.0 < scenario.reserve_frac < 1.0, "in (0, 1)"),
            ("recharge_slots", scenario.recharge_slots >= 1, "at least 1"),
            ("n_stations", scenario.n_stations == 4, "4 (one per quadrant)"),
            ("demand_intensity", scenario.demand_intensity > 0, "positive"),
            ("bandwidth_hz", scenario.bandwidth_hz > 0, "positive"),
        ]
        for key, ok, expected in checks:
            if not ok:
                raise ConfigError(f"{where}.{key}: expected {expected}, found {getattr(scenario, key)!r}")
        return scenario

    @property
    def noise_psd_w_per_hz(self) -> float:
        """Noise power spectral density N0 in W/Hz."""
        return 10.0 ** self.noise_psd_log10_w_per_hz

    def hash(self) -> str:
        """Hash of every constant; recorded with each result so the audit can compare scenarios."""
        return stable_hash(self)


_SUBSECTIONS = {("Scenario", "channel"): Channel, ("Scenario", "rotor"): Rotor, ("Scenario", "init"): InitConfig}


def load_config(path: str | Path = "config.yaml") -> dict:
    """Read config.yaml as a plain dict (validation of the whole file is the workflow schema's job)."""
    path = Path(path)
    try:
        with path.open() as fh:
            data = yaml.safe_load(fh)
    except FileNotFoundError as err:
        raise ConfigError(f"{path}: config file not found") from err
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level, found {type(data).__name__}")
    return data


def load_scenario(path: str | Path = "config.yaml") -> Scenario:
    """The Scenario of a config file."""
    data = load_config(path)
    if "scenario" not in data:
        raise ConfigError(f"{path}: missing top-level key 'scenario'")
    return Scenario.from_dict(data["scenario"])
