"""The scenario constants of docs/PROTOCOL.md §1 as one frozen dataclass tree (config.yaml ``scenario``).

``Scenario.from_dict`` builds it with the project's one typed builder (``dswm.config.build``): unknown or
missing keys and values of the wrong type stop with a message that names the key.
"""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any, Literal, Mapping

from dswm.config import ConfigError, build, load_yaml, stable_hash

CALIBRATE = "calibrate"
"""``scenario.demand_intensity: calibrate``: u is the value of the calibrate rule's record, read by every job that
needs it (``dswm.settings.calibrated_scenario``), instead of a number written in config.yaml."""

DEMO_INTENSITY = 65.58
"""The u the calibrate rule finds on the demo Milan data (docs/PROTOCOL.md §2). It stands in for ``calibrate``
only where there is no record to read: an environment built without a scenario, tests and benchmarks
(:func:`load_scenario` with ``standin=True``); no pipeline job uses it."""


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
    """W, aircraft weight, N."""
    air_density: float
    """rho_air, air density, kg/m^3."""
    rotor_radius_m: float
    """R, rotor radius, m."""
    disc_area_m2: float
    """A, rotor disc area, m^2."""
    blade_angular_velocity: float
    """Omega, blade angular velocity, rad/s."""
    tip_speed_mps: float
    """U_tip, tip speed of the rotor blade, m/s."""
    rotor_solidity: float
    """s, rotor solidity."""
    fuselage_drag_ratio: float
    """d0, fuselage drag ratio."""
    induced_power_correction: float
    """k, incremental correction factor of the induced power."""
    profile_drag_coefficient: float
    """delta, profile drag coefficient."""


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
    """K, UAV base stations."""
    altitude_m: float
    """h_fly, fixed flight altitude, m."""
    slot_s: float
    """Slot length, s (600: 10 min)."""
    slots_per_day: int
    """T, slots of a day; one episode is one day."""
    d_max_m: float
    """Largest displacement per slot, m (a move is norm-clipped to it)."""
    v_max_mps: float
    """Speed limit, m/s; also the speed of the return flight to a station."""
    carrier_hz: float
    """f_c, carrier frequency, Hz."""
    bandwidth_hz: float
    """B, bandwidth per UAV, Hz, split over its associated cells."""
    tx_power_w: float
    """P_k, transmit power per UAV, W."""
    noise_psd_log10_w_per_hz: float
    """log10 of the noise power spectral density N0 in W/Hz (-20.4: -174 dBm/Hz)."""
    r0_bps: float
    """r0, requested rate per user, bit/s."""
    u_peak: float
    """Fulfilment at which a cell counts as satisfied (the Jain index only)."""
    demand_intensity: float | Literal["calibrate"]
    """u; ``"calibrate"`` in settings that take it from the calibrate rule's record, which every job resolves to
    the number before it simulates (:attr:`intensity`)."""
    battery_j: float
    """E_batt, battery capacity, J."""
    reserve_frac: float
    """Fraction of E_batt below which a UAV returns to its nearest station."""
    recharge_slots: int
    """Slots spent charging, then active again at the station with a full battery."""
    n_stations: int
    """Charging stations, one at the centre of each quadrant of the area (4)."""
    reward_alpha: float
    """alpha, energy weight in the reward (paper eq. 7)."""
    reward_beta: float
    """beta, unserved-demand weight in the reward (paper eq. 7)."""
    obs_window: int
    """w: the observation holds the demand maps x_{t-w..t}."""
    channel: Channel
    """The air-to-ground channel (``scenario.channel``)."""
    rotor: Rotor
    """The rotary-wing power model (``scenario.rotor``)."""
    init: InitConfig
    """The initial state of every evaluated day (``scenario.init``)."""

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], *, where: str = "scenario") -> "Scenario":
        """Build from the ``scenario`` mapping of config.yaml; raises ConfigError naming the bad key."""
        fixed = {}
        if isinstance(data, Mapping) and "demand_intensity" in data:  # a number, or "calibrate"
            u = data["demand_intensity"]
            if u != CALIBRATE and (isinstance(u, bool) or not isinstance(u, (int, float)) or not math.isfinite(u)):
                raise ConfigError(f"config key {where}.demand_intensity: expected a positive number or "
                                  f"{CALIBRATE!r}, found {u!r}")
            fixed["demand_intensity"] = u if u == CALIBRATE else float(u)
            data = {k: v for k, v in data.items() if k != "demand_intensity"}
        scenario = build(cls, data, where, **fixed)
        u = scenario.demand_intensity
        checks = [
            ("n_uavs", scenario.n_uavs >= 1, "at least 1"),
            ("obs_window", 1 <= scenario.obs_window < scenario.slots_per_day,
             f"an integer in [1, {scenario.slots_per_day - 1}] (fewer than the {scenario.slots_per_day} slots of "
             f"{where}.slots_per_day)"),
            ("reserve_frac", 0.0 < scenario.reserve_frac < 1.0, "in (0, 1)"),
            ("recharge_slots", scenario.recharge_slots >= 1, "at least 1"),
            ("n_stations", scenario.n_stations == 4, "4 (one per quadrant)"),
            ("demand_intensity", u == CALIBRATE or u > 0, f"a positive number or {CALIBRATE!r}"),
            ("bandwidth_hz", scenario.bandwidth_hz > 0, "positive"),
        ]
        for key, ok, expected in checks:
            if not ok:
                raise ConfigError(f"config key {where}.{key}: expected {expected}, found {getattr(scenario, key)!r}")
        return scenario

    @property
    def calibrates(self) -> bool:
        """True when u is taken from the calibrate rule's record (``demand_intensity: calibrate``)."""
        return self.demand_intensity == CALIBRATE

    @property
    def intensity(self) -> float:
        """The demand intensity u as a number.

        Raises:
            ConfigError: u is still ``"calibrate"`` (the record has not been read).
        """
        if self.calibrates:
            raise ConfigError(f"scenario.demand_intensity is {CALIBRATE!r}: read u from the calibrate rule's record "
                              f"first (dswm.settings.calibrated_scenario)")
        return float(self.demand_intensity)

    @property
    def noise_psd_w_per_hz(self) -> float:
        """Noise power spectral density N0 in W/Hz."""
        return 10.0 ** self.noise_psd_log10_w_per_hz

    def hash(self) -> str:
        """Hash of every constant, u as the number used; recorded with each result so the audit can compare
        scenarios."""
        self.intensity  # noqa: B018 - refuses a scenario whose u is still "calibrate"
        return stable_hash(self)


def load_scenario(path: str | Path, *, standin: bool = False) -> Scenario:
    """The Scenario of a config file (its ``scenario`` section).

    Args:
        standin: with ``demand_intensity: calibrate``, use :data:`DEMO_INTENSITY` for u (a scenario to simulate
            without the calibrate rule's record); otherwise u stays ``"calibrate"``.
    """
    data = load_yaml(path)
    if "scenario" not in data:
        raise ConfigError(f"{path}: missing top-level key 'scenario'")
    scenario = Scenario.from_dict(data["scenario"])
    if standin and scenario.calibrates:
        scenario = dataclasses.replace(scenario, demand_intensity=DEMO_INTENSITY)
    return scenario
