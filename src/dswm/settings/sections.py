"""The typed sections of config.yaml other than the methods' and the scenario's: one frozen dataclass per section,
built by the project's one builder (``dswm.config.build``); ``figures`` and ``resources`` with the selected profile's
``budgets`` entry merged in (``dswm.config.with_budget``).
"""
from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Any, Mapping

from dswm.config import build, with_budget
from dswm.methods.search import SearchSettings

if TYPE_CHECKING:
    from dswm.settings.model import Settings


@dataclasses.dataclass(frozen=True, kw_only=True)
class EvalDayLimits:
    """At most this many of each split's evaluation days (None: every configured day)."""

    id: int | None
    """In-distribution (weekday) test days at most; None: every configured one."""
    ood: int | None
    """Out-of-distribution (holiday) test days at most; None: every configured one."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class RunSettings:
    """The selected profile (``profiles.<profile>``)."""

    datasets: tuple[str, ...]
    """The datasets the profile runs, in table order."""
    seeds: dict[str, tuple[int, ...]]
    """{dataset: its seeds}: one training and one evaluation job per seed."""
    eval_days: EvalDayLimits
    """How many of each split's test days are evaluated."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class EvaluationSettings:
    """config.yaml ``evaluation`` less the display setting (:class:`Display`)."""

    device: str
    """Torch device of the environment and the planners (``cpu``, ``cuda``)."""
    torch_threads: int
    """Torch threads per job (Snakemake runs one job per core)."""
    batch_days: bool
    """Step all evaluated days of a job as one batch where the controller allows it."""
    reuse_seed_independent: bool
    """Evaluate a method whose result the seed does not change (``Controller.deterministic``) once per dataset, at
    its first seed; the other seeds' evaluate jobs reuse that evaluation (:func:`dswm.settings.reused_seed`)."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class Runtime:
    """Where and on how many threads a job computes: the part of ``evaluation`` that training and calibration
    read (``batch_days`` concerns evaluation only)."""

    device: str
    """Torch device (``evaluation.device``)."""
    torch_threads: int
    """Torch threads per job (``evaluation.torch_threads``)."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class Display:
    """Settings that change how a job reports, never what it writes; passed beside a job's settings slice and
    not part of any rerun trigger."""

    progress_mininterval_s: float
    """tqdm refresh interval in a job's log (config.yaml ``evaluation.progress_mininterval_s``)."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class CalibrationSettings:
    dataset: str
    """The dataset on whose training days Static is run (PROTOCOL §2)."""
    target_served_ratio: float
    """The served ratio of Static that the calibrated u gives."""
    bracket: tuple[float, float]
    """The bisection interval (low, high) of u."""
    tolerance: float
    """Stop once the served ratio is this close to the target."""
    max_iter: int
    """Bisection steps at most (more is an error)."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class SelectionSettings:
    """config.yaml ``selection``: what the ``select`` rule compares on TRAINING days (docs/PROTOCOL.md §5)."""

    dataset: str
    """The dataset whose training days are used."""
    fit_days: int
    """The first ``fit_days`` training days fit the world model; the later training days validate."""
    search_candidates: tuple[SearchSettings, ...]
    """Candidate strengths of the shared BCD ``search`` (Greedy on the validation days)."""
    search_budget_ms: float
    """Largest Greedy planning time per day-slot a chosen search may cost."""
    planner_method: str
    """The method of ``methods.run`` whose planner's open values are chosen (``dswm``, Algorithm 1)."""
    gamma: tuple[float, ...]
    """Candidate planner discounts."""
    sigma0: tuple[float, ...]
    """Candidate initial sampling stds."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class MlflowHttp:
    """config.yaml ``mlflow.http``: how a tracking server's transient HTTP errors are retried (bounded)."""

    max_retries: int
    """Retries of a refused connection or a 408/429/5xx answer (MLflow allows at most 10)."""
    backoff_factor: int
    """Seconds of the first wait between tries, doubled at each further try."""
    timeout_s: int
    """Seconds each request waits for an answer."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class MlflowSettings:
    tracking_uri: str | None
    """A tracking server's URL (``http://host:port``), or None for the SQLite ``store`` (one machine)."""
    store: str
    """The SQLite tracking store used when ``tracking_uri`` is None."""
    artifacts: str
    """The experiment's artifact location (every run's result files)."""
    experiment: str
    """The one experiment every job logs its run to."""
    batch_size: int
    """Metrics per ``log_batch`` request (MLflow's limit)."""
    http: MlflowHttp
    """How a tracking server's transient HTTP errors are retried."""
    unlogged: str
    """Where a job whose tracking failed keeps its result files (``<unlogged>/<job key>/``)."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class SplitLabels:
    id: str
    """Column name of the in-distribution split (the paper's ``Weekday``)."""
    ood: str
    """Column name of the out-of-distribution split (the paper's ``Holiday``)."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class RoomSettings:
    """config.yaml ``tables.room``: the footnote on the room a forecast could fill and on the ladder of bounds."""

    low: str
    """The method that plans on the current map (Greedy)."""
    high: str
    """The method that plans on the true future maps (the perfect forecast)."""
    fill: tuple[str, ...]
    """The methods whose share of the room the footnote gives."""
    min_room: float
    """The smallest room whose share is given."""
    ladder: tuple[str, ...]
    """The references and bounds the footnote and room.csv give in order (Static -> Greedy -> Oracle -> Perfect ->
    Ceiling), per dataset and split."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class TablesSettings:
    main_dataset: str
    """The dataset of Table III (one the profile runs)."""
    decimals: int
    """Decimals of the printed served ratios."""
    split_labels: SplitLabels
    """Column names of the two evaluation splits."""
    class_order: tuple[str, ...]
    """The row groups (table classes) of Table III, top to bottom."""
    room: RoomSettings
    """The footnote on the room a forecast could fill."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class DoProbeSettings:
    """config.yaml ``figures.do_probe``: the counterfactual probe of paper Fig. ablation (b)."""

    methods: tuple[str, ...]
    """Methods whose imagined demand is scaled (those of ``methods.run``)."""
    scales: tuple[float, ...]
    """The factors s of the imagined demand at planning time (s = 1 is the method's own evaluation)."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class ScalingSettings:
    """config.yaml ``figures.scaling``: the two one-dimensional sweeps of paper Fig. scaling."""

    methods: tuple[str, ...]
    """Methods run in both sweeps (those of ``methods.run``)."""
    fleet_sizes: tuple[int, ...]
    """K of each run of the fleet sweep (the scenario's own K is the reference point)."""
    intensity_scales: tuple[float, ...]
    """Factors of the demand intensity u of each run of the intensity sweep."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class SampleEfficiencySettings:
    """config.yaml ``figures.sample_efficiency``: the test-day probe at fixed training checkpoints."""

    methods: tuple[str, ...]
    """Methods probed (those of ``methods.run`` that the ``train`` rule fits)."""
    fractions: tuple[float, ...]
    """Checkpoints as fractions of each method's training budget."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class WmQualitySettings:
    """config.yaml ``figures.wm_quality``."""

    horizon: int
    """Imagination steps of the demand-RMSE curve."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class ForesightSettings:
    """config.yaml ``figures.foresight``: demand source x planner (figure ``foresight``)."""

    datasets: tuple[str, ...]
    """Datasets of the grid (those the profile runs are drawn)."""
    rho: tuple[float, ...]
    """Anchoring values rho of the world-model rows besides each planner's own (``dswm.planner.rho``)."""
    eval_days: EvalDayLimits
    """How many of each split's test days the grid's extra runs evaluate (the methods' own cells are the main
    evaluations cut to the same days)."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class HeadroomSettings:
    """config.yaml ``figures.headroom``: Greedy, Perfect forecast and Ceiling over D_max x demand intensity
    (figure ``headroom``)."""

    datasets: tuple[str, ...]
    """Datasets of the map (those the profile runs are drawn)."""
    d_max_m: tuple[float, ...]
    """Largest displacement per slot of each column of the map, metres (the scenario's own is one of them)."""
    intensity_scales: tuple[float, ...]
    """Factors of the calibrated demand intensity u of each row of the map."""
    min_room: float
    """A regime whose room (Perfect - Greedy) reaches this is named in the CSV."""
    eval_days: EvalDayLimits
    """How many of each split's test days the map's extra runs evaluate."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class RoomFillSettings:
    """config.yaml ``figures.room_fill``: DSWM+, its persistence probe, Algorithm 1 and the candidate with anchoring
    per imagined step in one regime of the headroom map (figure ``room_fill``)."""

    dataset: str
    """The regime's dataset (one of ``figures.headroom.datasets``)."""
    d_max_m: float
    """The regime's largest displacement per slot, metres (one of ``figures.headroom.d_max_m``)."""
    intensity_scale: float
    """The regime's factor of the calibrated demand intensity u (one of ``figures.headroom.intensity_scales``)."""
    eval_days: EvalDayLimits
    """At most this many of each split's test days of the profile (``profiles.<p>.eval_days``; None: all of them)
    every run of the figure evaluates (Greedy and Perfect included)."""
    fit_days: int
    """Training days whose replay fits rho_k: the ``fit_days`` training days before the validation days."""
    validation_days: int
    """The last training days, held out as ``select`` holds them out: gamma is chosen on them."""
    gammas: tuple[float, ...]
    """Candidate planner discounts of the candidate (ties: the first)."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class FiguresSettings:
    """config.yaml ``figures`` merged with ``figures.budgets.<profile>``: the figures' dataset and the sizes of the
    extra runs behind them (none of which enters a table)."""

    dataset: str
    """The dataset of the extra runs and of the per-dataset figures (one the profile runs)."""
    seeds: tuple[int, ...]
    """Seeds of the extra runs."""
    eval_days: EvalDayLimits
    """How many of each split's test days the extra runs evaluate."""
    do_probe: DoProbeSettings
    """The counterfactual probe of paper Fig. ablation (b)."""
    scaling: ScalingSettings
    """The fleet-size and intensity sweeps of paper Fig. scaling."""
    sample_efficiency: SampleEfficiencySettings
    """The test-day probe at fixed training checkpoints."""
    wm_quality: WmQualitySettings
    """The world model's imagination-quality curve."""
    foresight: ForesightSettings
    """Demand source x planner on every dataset."""
    headroom: HeadroomSettings
    """The headroom map: D_max x demand intensity on some datasets."""
    room_fill: RoomFillSettings
    """DSWM+ where the room is: the share of the room each planner fills in one regime of the headroom map."""

    def present(self, names, settings: "Settings") -> list[str]:
        """The methods of ``names`` that ``methods.run`` evaluates on :attr:`dataset`, in the order given."""
        on = settings.methods_on(self.dataset)
        return [n for n in names if n in on]


def figures_settings(config: Mapping[str, Any], profile: str) -> FiguresSettings:
    """``figures`` of a validated config with the selected profile's ``figures.budgets`` entry merged in."""
    return _budgeted(FiguresSettings, config, "figures", profile)


def _budgeted(cls, config: Mapping[str, Any], name: str, profile: str):
    """The top-level section ``name`` of a validated config with its ``budgets.<profile>`` entry merged in, built as
    ``cls`` (an error names the section and the budget entry it came from)."""
    return build(cls, *with_budget(config[name], profile, name))


@dataclasses.dataclass(frozen=True, kw_only=True)
class JobResources:
    """What one job of a rule asks a cluster scheduler for (SLURM's ``--mem`` and ``--time``)."""

    mem_mb: int
    """Memory in MB."""
    runtime: int
    """Wall-time limit in minutes."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class ResourceSettings:
    """config.yaml ``resources`` merged with ``resources.budgets.<profile>`` (profiles/slurm, docs/CLUSTER.md)."""

    default: JobResources
    """Every rule that ``rules`` does not list."""
    rules: dict[str, JobResources]
    """{rule: its jobs' resources} for the rules that differ from ``default``."""
    gpu_slurm_extra: str
    """sbatch options a training job on a GPU adds (a constraint, a QoS); its GPU itself is the ``gpu`` resource."""
    start_order: tuple[str, ...] = ()
    """Methods whose train and evaluate jobs (main and extra) start before the others', the first first
    (scheduling only)."""

    def of(self, rule: str) -> JobResources:
        """The resources of ``rule``'s jobs."""
        return self.rules.get(rule, self.default)

    def priority(self, method: str) -> int:
        """The Snakemake ``priority`` of ``method``'s train and evaluate jobs (:func:`start_priority` of
        :attr:`start_order`)."""
        return start_priority(self.start_order, method)


def start_priority(order, method: str) -> int:
    """A Snakemake ``priority`` from a start order: ``len(order) - i`` for the i-th method of ``order`` (the first
    the highest; higher starts first), 0 for a method that is not listed."""
    order = list(order)
    return len(order) - order.index(method) if method in order else 0


def resource_settings(config: Mapping[str, Any], profile: str) -> ResourceSettings:
    """``resources`` of a validated config with the selected profile's ``resources.budgets`` entry merged in."""
    return _budgeted(ResourceSettings, config, "resources", profile)
