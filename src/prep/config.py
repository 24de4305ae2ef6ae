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

    norm_percentile: float
    """Percentile of the TRAINING cell-slot values of the crop that normalizes (99, docs/PROTOCOL.md §4)."""
    kappa_reference: str
    """Dataset whose training mean is the kappa reference (``milan``)."""
    top_share_frac: float
    """Fraction of cells in the "top cells" share statistic (0.05)."""


@dataclass(frozen=True, kw_only=True)
class FixedCrop:
    first_row: int
    """Grid row of tensor row 0, counted from the south."""
    first_col: int
    """Grid column of tensor column 0, counted from the west."""
    rows: int
    """Rows of the crop."""
    cols: int
    """Columns of the crop."""


@dataclass(frozen=True, kw_only=True)
class DensestCrop:
    rows: int
    """Rows of the window with the largest TRAINING total over the full grid."""
    cols: int
    """Columns of that window."""


@dataclass(frozen=True, kw_only=True)
class MilanDemo:
    seed: int
    """Demo random seed (each day's file also depends on its date only)."""
    noise_sigma: float
    """Per-slot log-normal noise factor."""
    day_level_sigma: float
    """Per-day, per-square level factor (day-to-day variation around the real profiles)."""
    field_sigma: float
    """Amplitude (log) of the residual field (prep.demo.milan); 0 switches it off."""
    field_tau_slots: float
    """The residual field's AR(1) e-folding time in 10-min slots."""
    field_smooth_cells: float
    """Std of the residual field's spatial Gaussian kernel, in squares."""
    extra_codes_mean: float
    """Mean extra country codes per square and slot besides 39 (Poisson, at most 4)."""
    blank_internet_frac: float
    """Share of extra-code lines with SMS/calls only (a blank internet field)."""


@dataclass(frozen=True, kw_only=True)
class ShanghaiDemo:
    seed: int
    """Demo random seed."""
    n_users: int
    """Users, each with a home and (70%) a work station."""
    sessions_per_user_day: float
    """Mean session starts per user and day (Poisson)."""
    n_base_stations: int
    """Base stations the sessions sit on."""
    centre_lat: float
    """Latitude of the centre of the dense core (People's Square)."""
    centre_lon: float
    """Longitude of the centre of the dense core."""
    centre_sigma_km: float
    """Spread (Gaussian std, km) of the core's stations."""
    core_share: float
    """Share of stations in the core; the rest spread over the whole box."""
    missing_location_frac: float
    """Share of rows with a blank latitude/longitude (dropped and counted)."""
    zero_location_frac: float
    """Share of rows at 0/0 (dropped and counted)."""
    end_before_start_frac: float
    """Share of rows whose end time precedes the start (dropped and counted)."""
    mean_duration_min: float
    """Mean of the exponential session length, minutes."""


@dataclass(frozen=True, kw_only=True)
class YJMobDemo:
    seed: int
    """Demo random seed."""
    n_users: int
    """Users of the synthetic city."""
    records_per_user_day: float
    """Mean records per user and day."""
    centre_xy: tuple[int, int]
    """Centre (x, y) of the synthetic city on the full grid."""
    home_sigma_cells: float
    """Spread of homes, in cells."""
    work_sigma_cells: float
    """Spread of workplaces and hubs around the centre, in cells."""
    n_hubs: int
    """Hubs (stations, malls): cells that concentrate visits."""
    hub_share: float
    """Share of workplaces at a hub."""
    hub_visit_frac: float
    """Share of daytime records at the user's favourite hub (doubled on the weekend)."""
    weekend_phases: tuple[int, ...]
    """Days d with d % 7 in this list are the demo's weekend."""
    masked_user_frac: float
    """Share of users whose last days are masked with ``masked_value``."""
    masked_first_day: int
    """First masked day of those users."""


@dataclass(frozen=True, kw_only=True)
class MilanConfig:
    source: Literal["demo", "raw"]
    """``demo`` writes and reads the synthetic files; ``raw`` reads the published ones (``raw_files``)."""
    raw_files: tuple[str, ...]
    """Paths or globs of the published files, relative to the working directory."""
    on_out_of_range: Literal["error", "drop"]
    """A record outside the grid or every segment: ``error`` stops preparation, ``drop`` counts it."""
    timezone: str
    """Time zone of the local days and 10-min slots (time_interval is UTC)."""
    cell_m: float
    """Side of a Milano GRID square, m."""
    full_rows: int
    """Rows of the published grid (id 1 = south-west corner)."""
    full_cols: int
    """Columns of the published grid (ids increase eastward along a row)."""
    crop: FixedCrop
    """The crop of the full grid that becomes the tensor."""
    split: Split
    """The temporal split into training and test segments (first and last day, inclusive)."""
    eval_days: EvalDays
    """The rules that pick the ID and OOD evaluation days from the test segment."""
    allow_empty_days: tuple[str, ...]
    """ISO dates of training/test days that may have no record (never an evaluation day)."""
    demo: MilanDemo
    """The demo files' generator settings (``source: demo``)."""


@dataclass(frozen=True, kw_only=True)
class ShanghaiConfig:
    source: Literal["demo", "raw"]
    """``demo`` writes and reads the synthetic files; ``raw`` reads the published ones (``raw_files``)."""
    raw_files: tuple[str, ...]
    """Paths or globs of the published files, relative to the working directory."""
    on_out_of_range: Literal["error", "drop"]
    """A record outside the grid or every segment: ``error`` stops preparation, ``drop`` counts it."""
    lat_min: float
    """Southern edge of the declared box; grid rows go northward from it."""
    lat_max: float
    """Northern edge of the declared box."""
    lon_min: float
    """Western edge of the declared box; grid columns go eastward from it."""
    lon_max: float
    """Eastern edge of the declared box."""
    cell_m: float
    """Cell side, m, counted from (lat_min, lon_min)."""
    crop: DensestCrop
    """The crop of the full grid that becomes the tensor."""
    window_slots: int
    """Trailing mean of session starts over this many slots (slot t and those before it)."""
    split: Split
    """The temporal split into training and test segments (first and last day, inclusive)."""
    eval_days: EvalDays
    """The rules that pick the ID and OOD evaluation days from the test segment."""
    allow_empty_days: tuple[str, ...]
    """ISO dates of training/test days that may have no session (never an evaluation day)."""
    demo: ShanghaiDemo
    """The demo files' generator settings (``source: demo``)."""


@dataclass(frozen=True, kw_only=True)
class YJMobConfig:
    source: Literal["demo", "raw"]
    """``demo`` writes and reads the synthetic files; ``raw`` reads the published ones (``raw_files``)."""
    raw_files: tuple[str, ...]
    """Paths or globs of the published files, relative to the working directory."""
    on_out_of_range: Literal["error", "drop"]
    """A record outside the grid or every segment: ``error`` stops preparation, ``drop`` counts it."""
    cell_m: float
    """Side of a published cell, m."""
    full_size: int
    """x and y run over 1..full_size."""
    masked_value: int
    """x = y = this value marks a masked record (dropped and counted)."""
    raw_slots_per_day: int
    """Published slots per day (30 min each; each is divided into its 10-min slots)."""
    n_days: int
    """Days d = 0..n_days-1 of the published file."""
    crop: DensestCrop
    """The crop of the full grid that becomes the tensor."""
    split: Split
    """The temporal split into training and test segments (first and last day, inclusive)."""
    week: WeekRecovery
    """How the week is recovered from the training daily totals."""
    eval_days: EvalDays
    """The rules that pick the ID and OOD evaluation days from the test segment."""
    allow_empty_days: tuple[int, ...]
    """Day numbers that may have no record (training days, or test days no eval rule can pick)."""
    demo: YJMobDemo
    """The demo files' generator settings (``source: demo``)."""


DatasetConfig = MilanConfig | ShanghaiConfig | YJMobConfig


def _check_days(cfg: DatasetConfig, dataset: str) -> None:
    """The split, evaluation days and empty-day allowance of a section built from config (at parse time)."""
    check_days(cfg, dataset)


_CLASSES = {"milan": MilanConfig, "shanghai": ShanghaiConfig, "yjmob": YJMobConfig}


@dataclass(frozen=True, kw_only=True)
class DatasetsConfig:
    common: CommonPrep
    """Settings shared by every dataset."""
    milan: MilanConfig
    """Telecom Italia Milan CDR, internet modality (the main dataset)."""
    shanghai: ShanghaiConfig
    """Shanghai Telecom sessions."""
    yjmob: YJMobConfig
    """YJMob100K dataset 1, distinct users per cell."""

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
