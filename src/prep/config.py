"""Typed, frozen configuration of the `datasets:` section of config.yaml.

Every key is required (config.yaml writes every default out); an unknown or missing key is an error that
names its dotted path. Building the section (or one dataset's) also checks each split, evaluation days and
``allow_empty_days`` (``prep.days.check_days``), so these mistakes stop the workflow when settings are
resolved. Build with `datasets_config(config["datasets"])`, or one dataset's section with
`dataset_from_plain(name, section)`. The split, evaluation-day and week-recovery sections live in ``prep.sections``,
below this module and ``prep.days``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from prep.days import check_days
from prep.sections import EvalDays, Split, WeekRecovery
from prep.typed import ConfigError, build

DATASETS = ("milan", "shanghai", "yjmob")


@dataclass(frozen=True, kw_only=True)
class CommonPrep:
    """Settings shared by every dataset."""

    norm_percentile: float  # percentile of TRAINING cell-slot values used to normalize (99 per docs/PROTOCOL.md §4)
    kappa_reference: str  # dataset whose training mean is the kappa reference ("milan")
    top_share_frac: float  # fraction of cells in the "top cells" share statistic (0.05)


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
    field_sigma: float  # amplitude (log) of the residual field (prep.demo.milan); 0 switches it off
    field_tau_slots: float  # its AR(1) e-folding time in 10-min slots
    field_smooth_cells: float  # std of its spatial Gaussian kernel in squares
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
    allow_empty_days: tuple[str, ...]  # ISO dates of training/test days that may have no record (never an eval day)
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
    allow_empty_days: tuple[str, ...]  # ISO dates of training/test days that may have no session (never an eval day)
    demo: ShanghaiDemo


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
    allow_empty_days: tuple[int, ...]  # day numbers d that may have no record (training days, or test days that
    #                                    no eval rule can pick; never an eval day)
    demo: YJMobDemo


DatasetConfig = MilanConfig | ShanghaiConfig | YJMobConfig


def _check_days(cfg: DatasetConfig, dataset: str) -> None:
    """The split, evaluation days and empty-day allowance of a section built from config (at parse time)."""
    check_days(cfg, dataset)


_CLASSES = {"milan": MilanConfig, "shanghai": ShanghaiConfig, "yjmob": YJMobConfig}


@dataclass(frozen=True, kw_only=True)
class DatasetsConfig:
    common: CommonPrep
    milan: MilanConfig
    shanghai: ShanghaiConfig
    yjmob: YJMobConfig

    def __post_init__(self) -> None:  # built by datasets_config and by dswm.settings.resolve
        for name in DATASETS:
            _check_days(getattr(self, name), name)


def datasets_config(section: dict) -> DatasetsConfig:
    """Builds the whole `datasets:` section.

    Args:
        section: config["datasets"] as loaded from YAML.
    Returns:
        DatasetsConfig with `common` and one config per dataset.
    """
    return build(DatasetsConfig, section, "datasets")


def dataset_from_plain(name: str, section: dict) -> DatasetConfig:
    """One dataset's typed section from its plain mapping (a job's settings slice, or config.yaml's)."""
    if name not in _CLASSES:
        raise ConfigError(f"unknown dataset {name!r}; expected one of {DATASETS}")
    cfg = build(_CLASSES[name], section, f"datasets.{name}")
    _check_days(cfg, name)
    return cfg


def common_from_plain(section: dict) -> CommonPrep:
    """``datasets.common`` from its plain mapping."""
    return build(CommonPrep, section, "datasets.common")
