"""Typed, frozen configuration of the `datasets:` section of config.yaml.

Every key is required (config.yaml writes every default out); an unknown or missing key is an error that
names its dotted path. Build with `datasets_config(config["datasets"])` or `dataset_config(config, name)`.
"""
from __future__ import annotations

import dataclasses
import types
import typing
from dataclasses import dataclass
from typing import Any, Literal

DATASETS = ("milan", "shanghai", "yjmob")


@dataclass(frozen=True, kw_only=True)
class CommonPrep:
    """Settings shared by every dataset."""

    norm_percentile: float  # percentile of TRAINING cell-slot values used to normalize (99 per SPEC 4)
    kappa_reference: str  # dataset whose training mean is the kappa reference ("milan")
    top_share_frac: float  # fraction of cells in the "top cells" share statistic (0.05)


@dataclass(frozen=True, kw_only=True)
class Segment:
    """A temporal segment, inclusive on both ends (ISO dates, or day numbers for YJMob)."""

    first: str
    last: str


@dataclass(frozen=True, kw_only=True)
class Split:
    train: tuple[str, str]
    test: tuple[str, str]

    def segments(self) -> dict[str, Segment]:
        """Returns {"train": Segment, "test": Segment}."""
        return {"train": Segment(first=self.train[0], last=self.train[1]),
                "test": Segment(first=self.test[0], last=self.test[1])}


@dataclass(frozen=True, kw_only=True)
class EvalRule:
    """How evaluation days are picked from the test segment.

    rule: "test_positions" (values = positions within the test segment), "first_weekdays" (the first
    `count` test days that are not (pseudo-)weekend) or "first_weekend" (the first `count` that are).
    """

    rule: Literal["test_positions", "first_weekdays", "first_weekend"]
    values: tuple[int, ...]
    count: int


@dataclass(frozen=True, kw_only=True)
class EvalDays:
    id: EvalRule
    ood: EvalRule


@dataclass(frozen=True, kw_only=True)
class FixedCrop:
    first_row: int  # first grid row counted from the south
    first_col: int  # first grid column counted from the west
    rows: int
    cols: int


@dataclass(frozen=True, kw_only=True)
class DensestCrop:
    rows: int  # window with the largest TRAINING total over the full grid
    cols: int


@dataclass(frozen=True, kw_only=True)
class MilanDemo:
    seed: int
    noise_sigma: float
    day_level_sigma: float
    extra_codes_mean: float
    blank_internet_frac: float


@dataclass(frozen=True, kw_only=True)
class ShanghaiDemo:
    seed: int
    n_users: int
    sessions_per_user_day: float
    n_base_stations: int
    centre_lat: float
    centre_lon: float
    centre_sigma_km: float
    core_share: float
    missing_location_frac: float
    zero_location_frac: float
    end_before_start_frac: float
    mean_duration_min: float


@dataclass(frozen=True, kw_only=True)
class YJMobDemo:
    seed: int
    n_users: int
    records_per_user_day: float
    centre_xy: tuple[int, int]
    home_sigma_cells: float
    work_sigma_cells: float
    n_hubs: int
    hub_share: float
    hub_visit_frac: float
    weekend_phases: tuple[int, ...]
    masked_user_frac: float
    masked_first_day: int


@dataclass(frozen=True, kw_only=True)
class MilanConfig:
    source: Literal["demo", "raw"]
    raw_files: tuple[str, ...]
    on_out_of_range: Literal["error", "drop"]
    timezone: str
    cell_m: float
    full_rows: int
    full_cols: int
    crop: FixedCrop
    split: Split
    eval_days: EvalDays
    demo: MilanDemo


@dataclass(frozen=True, kw_only=True)
class ShanghaiConfig:
    source: Literal["demo", "raw"]
    raw_files: tuple[str, ...]
    on_out_of_range: Literal["error", "drop"]
    lat_min: float
    lat_max: float
    lon_min: float
    lon_max: float
    cell_m: float
    crop: DensestCrop
    window_slots: int
    split: Split
    eval_days: EvalDays
    demo: ShanghaiDemo


@dataclass(frozen=True, kw_only=True)
class WeekRecovery:
    min_lag: int
    max_lag: int
    n_weekend_phases: int


@dataclass(frozen=True, kw_only=True)
class YJMobConfig:
    source: Literal["demo", "raw"]
    raw_files: tuple[str, ...]
    on_out_of_range: Literal["error", "drop"]
    cell_m: float
    full_size: int
    masked_value: int
    raw_slots_per_day: int
    n_days: int
    crop: DensestCrop
    split: Split
    week: WeekRecovery
    eval_days: EvalDays
    demo: YJMobDemo


DatasetConfig = MilanConfig | ShanghaiConfig | YJMobConfig
_CLASSES = {"milan": MilanConfig, "shanghai": ShanghaiConfig, "yjmob": YJMobConfig}


@dataclass(frozen=True, kw_only=True)
class DatasetsConfig:
    common: CommonPrep
    milan: MilanConfig
    shanghai: ShanghaiConfig
    yjmob: YJMobConfig


class ConfigError(ValueError):
    """A key of config.yaml is missing, unknown or of the wrong type."""


def _convert(tp: Any, value: Any, where: str) -> Any:
    """Converts a YAML value to the annotated type `tp`, raising ConfigError naming `where`."""
    origin = typing.get_origin(tp)
    if dataclasses.is_dataclass(tp):
        return _build(tp, value, where)
    if origin is Literal:
        if value not in typing.get_args(tp):
            raise ConfigError(f"config key {where}: expected one of {typing.get_args(tp)}, found {value!r}")
        return value
    if origin is tuple:
        args = typing.get_args(tp)
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"config key {where}: expected a list, found {value!r}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], v, f"{where}[{i}]") for i, v in enumerate(value))
        if len(value) != len(args):
            raise ConfigError(f"config key {where}: expected {len(args)} items, found {len(value)}")
        return tuple(_convert(a, v, f"{where}[{i}]") for i, (a, v) in enumerate(zip(args, value)))
    if origin in (typing.Union, types.UnionType):
        raise ConfigError(f"config key {where}: unsupported union type")
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"config key {where}: expected a number, found {value!r}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"config key {where}: expected an integer, found {value!r}")
        return value
    if tp is str:
        if isinstance(value, bool) or not isinstance(value, (str, int)):
            raise ConfigError(f"config key {where}: expected a string, found {value!r}")
        return str(value)
    raise ConfigError(f"config key {where}: unsupported type {tp}")


def _build(cls: type, mapping: Any, where: str) -> Any:
    """Builds dataclass `cls` from a mapping, every field required, no unknown keys."""
    if not isinstance(mapping, dict):
        raise ConfigError(f"config key {where}: expected a mapping, found {mapping!r}")
    hints = typing.get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls)]
    unknown = sorted(set(mapping) - set(names))
    if unknown:
        raise ConfigError(f"config key {where}: unknown key(s) {unknown}; expected {names}")
    missing = [n for n in names if n not in mapping]
    if missing:
        raise ConfigError(f"config key {where}: missing key(s) {missing}")
    return cls(**{n: _convert(hints[n], mapping[n], f"{where}.{n}") for n in names})


def datasets_config(section: dict) -> DatasetsConfig:
    """Builds the whole `datasets:` section.

    Args:
        section: config["datasets"] as loaded from YAML.
    Returns:
        DatasetsConfig with `common` and one config per dataset.
    """
    return _build(DatasetsConfig, section, "datasets")


def dataset_config(config: dict, name: str) -> DatasetConfig:
    """Builds one dataset's config from the full config dict (config["datasets"][name])."""
    if name not in _CLASSES:
        raise ConfigError(f"unknown dataset {name!r}; expected one of {DATASETS}")
    try:
        section = config["datasets"][name]
    except (KeyError, TypeError) as exc:
        raise ConfigError(f"config key datasets.{name} is missing") from exc
    return _build(_CLASSES[name], section, f"datasets.{name}")


def common_config(config: dict) -> CommonPrep:
    """Builds datasets.common from the full config dict."""
    try:
        section = config["datasets"]["common"]
    except (KeyError, TypeError) as exc:
        raise ConfigError("config key datasets.common is missing") from exc
    return _build(CommonPrep, section, "datasets.common")
