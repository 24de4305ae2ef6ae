"""The scenario constants of docs/PROTOCOL.md §1 as one frozen dataclass tree (config.yaml ``scenario``).

``Scenario.from_dict`` builds it with the project's one typed builder (``dswm.config.build``): unknown or
missing keys and values of the wrong type stop with a message that names the key.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Mapping

from dswm.config import ConfigError, build, load_yaml, stable_hash


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
    """All scenario constants of docs/PROTOCOL.md §1."""

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
        scenario = build(cls, data, where)
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


def load_scenario(path: str | Path) -> Scenario:
    """The Scenario of a config file (its ``scenario`` section)."""
    data = load_yaml(path)
    if "scenario" not in data:
        raise ConfigError(f"{path}: missing top-level key 'scenario'")
    return Scenario.from_dict(data["scenario"])
