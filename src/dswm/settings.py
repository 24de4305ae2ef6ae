"""The settings of a run, resolved once: schema validation, profile selection, one typed :class:`Settings`.

``config.yaml`` holds every section; ``profiles:`` holds the three sizes of the same pipeline (demo, smoke,
paper). :func:`resolve` validates the file against ``workflow/schemas/config.schema.yaml``, selects the profile
and builds every section with the one typed builder (``dswm.config.build``), the methods' own settings
included. It runs once, while Snakemake parses the workflow, so a bad config stops the run before any job
starts, with a message that names the key, what was expected and what was found.

Jobs never see config.yaml: each rule passes its job the slice of :class:`Settings` the job reads, in canonical
form (:func:`dswm.config.canonical_json`, sorted keys), and that slice is the rule's rerun trigger. The slices
are built here (``*_slice``) and read back in the job by the same builder. Settings that change only how a
job reports (the progress bar's refresh interval; where and how its MLflow run is logged, :func:`tracking`) are
passed beside the slice as a typed object, which Snakemake does not compare, so changing them reruns nothing
(docs/PIPELINE.md).
"""
from __future__ import annotations

import copy
import dataclasses
import difflib
import json
import math
from pathlib import Path
from typing import Any, Iterable, Mapping

import jsonschema
import yaml

from dswm.config import ConfigError, ConfigSources, build, canonical_json, lookup, merge, stable_hash, to_plain
from dswm.methods import registry
from dswm.methods.search import SearchSettings
from dswm.sim.scenario import CALIBRATE, Scenario
from prep.config import DATASETS, DatasetsConfig

def load_schema(path: str | Path) -> dict:
    """Read the YAML JSON-schema of config.yaml."""
    with Path(path).open() as fh:
        return yaml.safe_load(fh)


def _key(path: Iterable[Any]) -> str:
    """Dotted key of a path into the config, e.g. ``profiles.demo.seeds.milan[0]``."""
    out = ""
    for part in path:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out or "(top level)"


def _describe(schema: Mapping[str, Any]) -> str:
    """The expected form of a value, from the schema's description or its type keywords."""
    if "description" in schema:
        return str(schema["description"])
    if "enum" in schema:
        return "one of " + ", ".join(repr(v) for v in schema["enum"])
    kind = schema.get("type", "a value")
    kind = " or ".join(kind) if isinstance(kind, list) else kind
    bounds = [f"{word} {schema[k]}" for k, word in (("minimum", ">="), ("maximum", "<="),
                                                   ("exclusiveMinimum", ">"), ("minItems", "with at least"))
              if k in schema]
    return f"{kind}" + (f" ({', '.join(bounds)})" if bounds else "")


def _message(err: jsonschema.ValidationError, source: str) -> str:
    """One readable line for a schema violation: the key, what was expected, what was found."""
    where = _key(err.absolute_path)
    if err.validator == "additionalProperties":
        allowed = sorted(err.schema.get("properties", {}))
        unknown = sorted(set(err.instance) - set(allowed))
        lines = []
        for name in unknown:
            if err.schema.get("patternProperties"):
                pattern = ", ".join(err.schema["patternProperties"])
                lines.append(f"{source}: key '{_key([*err.absolute_path, name])}' is not a valid name "
                             f"(expected a name matching {pattern})")
                continue
            near = difflib.get_close_matches(name, allowed, n=1)
            hint = (f"; did you mean '{near[0]}'?" if near else
                    "; a new setting is declared in workflow/schemas/config.schema.yaml")
            lines.append(f"{source}: unknown key '{_key([*err.absolute_path, name])}' (expected one of "
                         f"{', '.join(allowed)}){hint}")
        return "\n".join(lines)
    if err.validator == "required":
        missing = err.message.split("'")[1]
        sub = err.schema.get("properties", {}).get(missing, {})
        return f"{source}: missing key '{_key([*err.absolute_path, missing])}' (expected {_describe(sub)})"
    return f"{source}: key '{where}' must be {_describe(err.schema)}; found {err.instance!r}"


def validate_config(config: Mapping[str, Any], schema: Mapping[str, Any], *, source: str = "config.yaml",
                    sources: ConfigSources | None = None) -> None:
    """Check ``config`` against the schema; raise ConfigError listing every violation, one per line.

    Args:
        config: the parsed config.yaml (with any ``--configfile`` and ``--config`` overrides applied).
        schema: the parsed workflow/schemas/config.schema.yaml.
        source: file name used in messages.
        sources: where each value came from (:class:`dswm.config.ConfigSources`); each line then names the layer
            of its key instead of ``source``, and a string that ``--config`` passed says so.
    """
    validator = jsonschema.Draft202012Validator(schema)
    errors = sorted(validator.iter_errors(config), key=lambda e: (list(map(str, e.absolute_path)), e.message))
    if not errors:
        return
    lines = []
    for err in errors:
        line = _message(err, source)
        if sources is not None:
            line = sources.relabel(line)
            if isinstance(err.instance, str) and sources.of(list(err.absolute_path)) == ConfigSources.CLI:
                line += (f" (--config passed it as the string {err.instance!r}: Snakemake reads a value nested in "
                         f"--config as a string, taken here as a number, boolean or null only where the schema "
                         f"expects one)")
        lines.append(line)
    raise ConfigError("invalid configuration:\n" + "\n".join(lines))


def coerce_cli_strings(config: Mapping[str, Any], schema: Mapping[str, Any], cli: Mapping[str, Any]) -> dict:
    """``config`` with each string that ``--config`` passed inside a mapping (Snakemake reads nested values as
    strings: ``scenario={"n_uavs": 3}`` arrives as ``{"n_uavs": "3"}``) read as YAML where the schema refuses the
    string and YAML reads it as a number, a boolean or null; every other value as it is.

    Args:
        config: the merged config.
        schema: the JSON schema.
        cli: the ``--config`` overrides (``workflow.config_settings.config``).
    """
    out = copy.deepcopy(dict(config))
    validator = jsonschema.Draft202012Validator(schema)
    while True:
        changed = False
        for err in validator.iter_errors(out):
            path = list(err.absolute_path)
            given, value = lookup(cli, path)
            if len(path) < 2 or not given or not isinstance(value, str) or err.instance != value:
                continue
            try:
                read = yaml.safe_load(value)
            except yaml.YAMLError:
                continue
            if read is not None and not isinstance(read, (bool, int, float)):
                continue
            node = out
            for part in path[:-1]:
                node = node[part]
            node[path[-1]] = read
            changed = True
        if not changed:
            return out


SCHEMA = Path(__file__).resolve().parents[2] / "workflow" / "schemas" / "config.schema.yaml"
"""The JSON schema of config.yaml."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class EvalDayLimits:
    """At most this many of each split's evaluation days (None: every configured day)."""

    id: int | None
    ood: int | None


@dataclasses.dataclass(frozen=True, kw_only=True)
class RunSettings:
    """The selected profile (``profiles.<profile>``)."""

    datasets: tuple[str, ...]
    seeds: dict[str, tuple[int, ...]]
    eval_days: EvalDayLimits


@dataclasses.dataclass(frozen=True, kw_only=True)
class EvaluationSettings:
    """config.yaml ``evaluation`` less the display setting (:class:`Display`)."""

    device: str
    torch_threads: int
    batch_days: bool


@dataclasses.dataclass(frozen=True, kw_only=True)
class Runtime:
    """Where and on how many threads a job computes: the part of ``evaluation`` that training and calibration
    read (``batch_days`` concerns evaluation only)."""

    device: str
    torch_threads: int


@dataclasses.dataclass(frozen=True, kw_only=True)
class Display:
    """Settings that change how a job reports, never what it writes; passed beside a job's settings slice and
    not part of any rerun trigger."""

    progress_mininterval_s: float
    """tqdm refresh interval in a job's log (config.yaml ``evaluation.progress_mininterval_s``)."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class CalibrationSettings:
    dataset: str
    target_served_ratio: float
    bracket: tuple[float, float]
    tolerance: float
    max_iter: int


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
    backoff_factor: int
    timeout_s: int


@dataclasses.dataclass(frozen=True, kw_only=True)
class MlflowSettings:
    tracking_uri: str | None
    """A tracking server's URL (``http://host:port``), or None for the SQLite ``store`` (one machine)."""
    store: str
    artifacts: str
    experiment: str
    batch_size: int
    http: MlflowHttp
    unlogged: str
    """Where a job whose tracking failed keeps its result files (``<unlogged>/<job key>/``)."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class SplitLabels:
    id: str
    ood: str


@dataclasses.dataclass(frozen=True, kw_only=True)
class RoomSettings:
    """config.yaml ``tables.room``: the footnote on the room a forecast could fill."""

    low: str
    """The method that plans on the current map (Greedy)."""
    high: str
    """The method that plans on the true future maps (the perfect forecast)."""
    fill: tuple[str, ...]
    """The methods whose share of the room the footnote gives."""
    min_room: float
    """The smallest room whose share is given."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class TablesSettings:
    main_dataset: str
    decimals: int
    split_labels: SplitLabels
    class_order: tuple[str, ...]
    room: RoomSettings


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
    fleet_sizes: tuple[int, ...]
    """K of each run of the fleet sweep (the scenario's own K is the reference point)."""
    intensity_scales: tuple[float, ...]
    """Factors of the demand intensity u of each run of the intensity sweep."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class SampleEfficiencySettings:
    """config.yaml ``figures.sample_efficiency``: the test-day probe at fixed training checkpoints."""

    methods: tuple[str, ...]
    fractions: tuple[float, ...]
    """Checkpoints as fractions of each method's training budget."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class WmQualitySettings:
    """config.yaml ``figures.wm_quality``."""

    horizon: int
    """Imagination steps of the demand-RMSE curve."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class FiguresSettings:
    """config.yaml ``figures`` merged with ``figures.budgets.<profile>``: the figures' dataset and the sizes of the
    extra runs behind them (none of which enters a table)."""

    dataset: str
    seeds: tuple[int, ...]
    eval_days: EvalDayLimits
    do_probe: DoProbeSettings
    scaling: ScalingSettings
    sample_efficiency: SampleEfficiencySettings
    wm_quality: WmQualitySettings

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
    section = dict(config[name])
    budgets = section.pop("budgets") or {}
    key = f"{name} (with {name}.budgets.{profile})" if profile in budgets else name
    return build(cls, merge(section, budgets.get(profile)), key)


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
    gpu_slurm_extra: str
    """sbatch options a training job on a GPU adds (a constraint, a QoS); its GPU itself is the ``gpu`` resource."""

    def of(self, rule: str) -> JobResources:
        """The resources of ``rule``'s jobs."""
        return self.rules.get(rule, self.default)


def resource_settings(config: Mapping[str, Any], profile: str) -> ResourceSettings:
    """``resources`` of a validated config with the selected profile's ``resources.budgets`` entry merged in."""
    return _budgeted(ResourceSettings, config, "resources", profile)


@dataclasses.dataclass(frozen=True, kw_only=True)
class MethodSettings:
    """One method of ``methods.run``: its registration and its typed settings."""

    name: str
    target: str
    """The controller class, "package.module:ClassName"."""
    label: str
    """Row label in the tables."""
    table_class: str
    """Class column of Table III."""
    learns: bool
    """Trained by the ``train`` rule before evaluation."""
    training_source: str | None
    """The method whose trained model this one evaluates (itself, or an earlier one with identical training);
    None for a method that does not learn."""
    options: Any
    """The typed settings of the controller class (its ``options_type``), or None."""
    only_on: tuple[str, ...] | None = None
    """The datasets it is evaluated on (``methods.only_on``); None: every dataset of the profile."""

    @property
    def controller_class(self):
        return registry.load_class(self.target, key=f"methods.{self.name}")

    @property
    def spec(self) -> registry.MethodSpec:
        """The method's registration: class path, table label and table class."""
        return registry.MethodSpec(name=self.name, target=self.target, label=self.label, table_class=self.table_class)

    @classmethod
    def from_plain(cls, data: Mapping[str, Any], where: str = "method") -> "MethodSettings":
        """Back from :func:`dswm.config.to_plain` form; the options are rebuilt as the class's typed settings."""
        entry = build(cls, data, where)
        options = entry.controller_class.options_from_plain(name=entry.name, data=data["options"],
                                                            where=f"{where}.options")
        return dataclasses.replace(entry, options=options)


@dataclasses.dataclass(frozen=True, kw_only=True)
class Settings:
    """Every setting of a run under its selected profile, typed; built once by :func:`resolve`."""

    profile: str
    run: RunSettings
    scenario: Scenario
    evaluation: EvaluationSettings
    methods: dict[str, MethodSettings]
    """The methods of ``methods.run``, in that order (table order within a table class)."""
    calibration: CalibrationSettings
    selection: SelectionSettings | None
    """None in the audit's slice (the audit reads no selection)."""
    mlflow: MlflowSettings | None
    """None in the audit's slice (where a run is logged changes no result the audit checks)."""
    tables: TablesSettings
    figures: FiguresSettings | None = None
    """None in a job's slice that reads no figure setting (the audit's)."""
    resources: ResourceSettings | None = None
    """What each rule's jobs ask a cluster for; None in the audit's slice (where a job runs changes no result)."""
    datasets: DatasetsConfig
    display: Display | None
    """None in a job's slice: display settings travel beside it."""

    def seeds(self, dataset: str) -> list[int]:
        """Seeds of ``dataset`` in the selected profile."""
        return list(self.run.seeds[dataset])

    def methods_on(self, dataset: str) -> list[str]:
        """The methods evaluated on ``dataset``, in ``methods.run`` order (``methods.only_on`` may restrict one)."""
        return [m.name for m in self.methods.values() if m.only_on is None or dataset in m.only_on]

    def jobs(self) -> list[tuple[str, str, int]]:
        """Every (dataset, method, seed) evaluation job of the selected profile, in table order."""
        return [(ds, m, s) for ds in self.run.datasets for m in self.methods_on(ds) for s in self.seeds(ds)]

    def training_sources(self) -> dict[str, str]:
        """{learning method: the method whose trained model it evaluates}."""
        return {m.name: m.training_source for m in self.methods.values() if m.learns}

    def trained(self) -> list[str]:
        """The learning methods the ``train`` rule fits (their own training source)."""
        return [m.name for m in self.methods.values() if m.learns and m.training_source == m.name]

    def hash(self) -> str:
        """Hash of these settings (display settings aside); tags the audit report."""
        return stable_hash(to_plain(dataclasses.replace(self, display=None)), length=12)

    @classmethod
    def from_plain(cls, data: Mapping[str, Any], where: str = "settings") -> "Settings":
        """Back from :func:`dswm.config.to_plain` form (a job's slice); method settings typed by their class."""
        fixed = {"methods": {name: MethodSettings.from_plain(m, f"{where}.methods.{name}")
                             for name, m in data["methods"].items()},
                 "scenario": Scenario.from_dict(data["scenario"], where=f"{where}.scenario")}
        return build(cls, {k: v for k, v in data.items() if k not in fixed}, where, **fixed)


def select_profile(config: Mapping[str, Any]) -> dict:
    """The selected ``profiles.<profile>`` entry of a validated config."""
    name = config["profile"]
    profiles = config["profiles"]
    if name not in profiles:
        raise ConfigError(f"config.yaml: key 'profile' must be one of {', '.join(profiles)}; found {name!r} "
                          f"(select one with --config profile=NAME)")
    return profiles[name]


def _methods(config: Mapping[str, Any], profile: str) -> dict[str, MethodSettings]:
    """Every method of ``methods.run`` with its class, typed settings and training source."""
    section = config["methods"]
    only_on = dict(section.get("only_on") or {})
    for name, datasets in only_on.items():
        if name not in section["run"]:  # a method left out of `run` keeps its entry, unused
            if name not in registry.BUILTIN and name not in section.get("user", {}):
                raise ConfigError(f"config.yaml: key 'methods.only_on.{name}' names {name!r}, which is not a "
                                  f"registered method (expected one of {', '.join(sorted(registry.BUILTIN))}, or a "
                                  f"user method of 'methods.user')")
            continue
        ran = [d for d in datasets if d in config["profiles"][profile]["datasets"]]
        if not ran:
            raise ConfigError(f"config.yaml: key 'methods.only_on.{name}' is {list(datasets)}, none of which profile "
                              f"{profile!r} runs (profiles.{profile}.datasets: "
                              f"{', '.join(config['profiles'][profile]['datasets'])}); expected at least one of "
                              f"them, or {name!r} left out of 'methods.run'")
    found: dict[str, tuple] = {}
    for name in section["run"]:
        s, cls = registry.lookup(name, section)
        found[name] = (s, cls, cls.options_from_config(name=name, config=config, profile=profile))
    sources = registry.training_sources({n: (cls, opt) for n, (_, cls, opt) in found.items() if cls.learns})
    return {n: MethodSettings(name=n, target=s.target, label=s.label, table_class=s.table_class,
                              learns=bool(cls.learns), training_source=sources.get(n), options=opt,
                              only_on=tuple(only_on[n]) if n in only_on else None)
            for n, (s, cls, opt) in found.items()}


def resolve(config: Mapping[str, Any], *, root: str | Path | None = None, schema: str | Path | None = None,
            sources: ConfigSources | None = None) -> Settings:
    """Validate config.yaml (with any ``--configfile`` and ``--config`` overrides) and resolve it into one typed
    :class:`Settings`.

    Args:
        config: the parsed config mapping.
        root: where ``datasets.<name>.raw_files`` are looked up; None skips that check (a job's own files).
        schema: the JSON schema (default :data:`SCHEMA`).
        sources: where each value came from (config.yaml, a ``--configfile``, ``--config``); messages name it, and
            the strings ``--config`` passed are read as numbers where the schema expects them
            (:func:`coerce_cli_strings`). None: every value is config.yaml's.

    Raises:
        ConfigError: every schema violation, one per line; or the first cross-key mistake (a profile's dataset
            without a section or seeds, an unregistered method, a merged DSWM planner with n_elites > n_samples,
            a ``tables.main_dataset`` the profile does not run, raw files that are not there).
    """
    sources = sources or ConfigSources()
    try:
        return _resolve(config, root=root, schema=load_schema(schema or SCHEMA), sources=sources)
    except ConfigError as err:
        raise ConfigError(sources.relabel(str(err))) from None


def _resolve(config: Mapping[str, Any], *, root: str | Path | None, schema: Mapping[str, Any],
             sources: ConfigSources) -> Settings:
    """:func:`resolve` once the schema is read; its errors say config.yaml (relabelled by the caller)."""
    cli = dict(sources.layers).get(ConfigSources.CLI)
    if cli:
        config = coerce_cli_strings(config, schema, cli)
    validate_config(config, schema, sources=sources)
    profile = str(config["profile"])
    run = select_profile(config)
    check_profile_datasets(config, run)
    evaluation = dict(config["evaluation"])
    display = Display(progress_mininterval_s=float(evaluation.pop("progress_mininterval_s")))
    settings = Settings(
        profile=profile,
        run=build(RunSettings, run, f"profiles.{profile}"),
        scenario=Scenario.from_dict(config["scenario"]),
        evaluation=build(EvaluationSettings, evaluation, "evaluation"),
        methods=_methods(config, profile),
        calibration=build(CalibrationSettings, config["calibration"], "calibration"),
        selection=build(SelectionSettings, config["selection"], "selection"),
        mlflow=build(MlflowSettings, config["mlflow"], "mlflow"),
        tables=build(TablesSettings, config["tables"], "tables"),
        figures=figures_settings(config, profile),
        resources=resource_settings(config, profile),
        datasets=build(DatasetsConfig, config["datasets"], "datasets"),
        display=display)
    if settings.tables.main_dataset not in settings.run.datasets:
        raise ConfigError(f"config.yaml: key 'tables.main_dataset' is {settings.tables.main_dataset!r}, which "
                          f"profile {profile!r} does not run (profiles.{profile}.datasets: "
                          f"{', '.join(settings.run.datasets)})")
    check_figures(settings)
    if root is not None:
        check_raw_files(settings, root)
    return settings


def check_figures(settings: Settings) -> None:
    """``figures.dataset`` is one the profile runs, and every method ``figures`` names is registered."""
    fig = settings.figures
    if fig.dataset not in settings.run.datasets:
        raise ConfigError(f"config.yaml: key 'figures.dataset' is {fig.dataset!r}, which profile "
                          f"{settings.profile!r} does not run (profiles.{settings.profile}.datasets: "
                          f"{', '.join(settings.run.datasets)})")
    for key, names in (("do_probe", fig.do_probe.methods), ("scaling", fig.scaling.methods),
                       ("sample_efficiency", fig.sample_efficiency.methods)):
        for name in names:
            if name not in registry.BUILTIN and name not in settings.methods:
                raise ConfigError(f"config.yaml: key 'figures.{key}.methods' names {name!r}, which is not a "
                                  f"registered method (expected one of {', '.join(sorted(registry.BUILTIN))})")


def check_profile_datasets(config: Mapping[str, Any], run: Mapping[str, Any]) -> None:
    """Every dataset the profile runs has a ``datasets:`` section and a seed list."""
    known = [d for d in config.get("datasets", {}) if d in DATASETS]
    for ds in run["datasets"]:
        if ds not in known:
            raise ConfigError(f"config.yaml: key 'profiles.{config['profile']}.datasets' names {ds!r}, which has "
                              f"no section under 'datasets' (expected one of {', '.join(sorted(known))})")
        if ds not in run["seeds"]:
            raise ConfigError(f"config.yaml: key 'profiles.{config['profile']}.seeds.{ds}' is missing "
                              f"(expected a non-empty list of integer seeds, e.g. [0, 1])")


def check_raw_files(settings: Settings, root: str | Path) -> None:
    """Every dataset with ``source: raw`` that the profile runs has its raw files on disk.

    Args:
        settings: the resolved settings.
        root: the directory the paths and globs of ``datasets.<name>.raw_files`` are relative to.
    """
    root = Path(root)
    for ds in settings.run.datasets:
        section = getattr(settings.datasets, ds)
        if section.source != "raw":
            continue
        for i, pattern in enumerate(section.raw_files):
            path = Path(pattern)
            base = path if path.is_absolute() else root / path
            if any(c in str(pattern) for c in "*?["):
                anchor = Path(base.anchor)
                found = list(anchor.glob(str(base.relative_to(anchor))))
            else:
                found = [base] if base.exists() else []
            if not found:
                raise ConfigError(f"config.yaml: key 'datasets.{ds}.raw_files[{i}]' = {pattern!r} matches no file "
                                  f"under {root} (expected the published raw file(s) of {ds}; download them, or "
                                  f"set 'datasets.{ds}.source: demo')")


@dataclasses.dataclass(frozen=True)
class Untracked:
    """A value a rule passes its job that is not part of its rerun trigger (Snakemake compares only plain
    params): how a job reports or tags its run, never what it computes."""

    value: Any


def evaluated_as(settings: Settings, method: str) -> list[str]:
    """The methods whose evaluations load the model that ``method`` trains (an MLflow tag of its train run)."""
    return [m for m, src in settings.training_sources().items() if src == method] or [method]


# ---- the demand intensity u: a number of config.yaml, or the calibrate rule's record -----------------------
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


def needs_gpu(settings: Settings, method: str | None) -> bool:
    """True when a job of ``method`` (None: a job without a method) runs torch on a CUDA device: its own ``device``
    setting (the DSWM methods' ``dswm.device``) or ``evaluation.device`` (the environment's) says cuda."""
    devices = [settings.evaluation.device]
    if method is not None and method in settings.methods:
        devices.append(getattr(settings.methods[method].options, "device", None) or "cpu")
    return any(str(d).startswith("cuda") for d in devices)


# ---- the slices each rule passes its job ----------------------------------------------------------------
def param(obj: Any) -> str:
    """A rule's ``params`` value: ``obj`` in canonical JSON (equal settings give equal text)."""
    return canonical_json(obj)


def read_param(text: str) -> dict:
    """A job's side of :func:`param`: the plain mapping back."""
    return json.loads(text)


def runtime(settings: Settings) -> dict:
    """The :class:`Runtime` part of ``evaluation``, plain."""
    return {"device": settings.evaluation.device, "torch_threads": settings.evaluation.torch_threads}


def prep_slice(settings: Settings, dataset: str) -> dict:
    """What the ``demo_raw`` and ``prepare`` jobs of ``dataset`` read: its section and the common one."""
    return {"dataset": dataset, "settings": to_plain(getattr(settings.datasets, dataset)),
            "common": to_plain(settings.datasets.common)}


def eda_slice(settings: Settings) -> dict:
    """What the ``eda`` job reads: the share of cells of the "top cells" statistic."""
    return {"top_share_frac": settings.datasets.common.top_share_frac}


def mlflow_slice(settings: Settings) -> dict:
    """The rerun trigger of the ``mlflow_init`` job: the experiment's name (:func:`experiment_slice`). Where it creates
    the store and the experiment (``tracking_uri`` or ``store``, ``artifacts``) and how it asks a server (``http``)
    travel beside it (:func:`tracking`): a new store or server reruns no job, the workflow's ``onstart`` creates
    them there before any job logs."""
    return experiment_slice(settings)


def experiment_slice(settings: Settings) -> dict:
    """The part of ``mlflow`` in the slice of a job that logs a run: the experiment's name alone (a renamed
    experiment receives every job's run again). The rest of the section travels beside the slice as
    :func:`tracking`, so a change of the server, the store, the batch size or the HTTP retries reruns no job."""
    return {"experiment": settings.mlflow.experiment}


def tracking(settings: Settings) -> "Untracked":
    """The whole ``mlflow`` section, plain, as an :class:`Untracked` param (``params.tracking``): where and how a job
    logs its run, never what it computes."""
    return Untracked(to_plain(settings.mlflow))


def calibrate_slice(settings: Settings) -> dict:
    """What the ``calibrate`` job reads: the calibration, the scenario less the value it calibrates, and the
    device and threads (:class:`Runtime`)."""
    scenario = to_plain(settings.scenario)
    scenario.pop("demand_intensity")
    return {"calibration": to_plain(settings.calibration), "scenario": scenario, "runtime": runtime(settings)}


def train_slice(settings: Settings, method: str, dataset: str | None = None, seed: int | None = None) -> dict:
    """What a ``train`` job of ``method`` reads: the profile, the scenario, the device and threads
    (:class:`Runtime`), the MLflow experiment (:func:`experiment_slice`), and the method with only its training
    settings (so decision-time settings never retrain); for a job of the sample-efficiency probe (:func:`probe_jobs`,
    given its ``dataset`` and ``seed``) also ``snapshots``: {"fractions": ``figures.sample_efficiency.fractions``}."""
    m = settings.methods[method]
    cls = m.controller_class
    entry = dataclasses.replace(m, options=cls.training_settings(m.options))
    job = {"profile": settings.profile, "scenario": to_plain(settings.scenario), "runtime": runtime(settings),
           "mlflow": experiment_slice(settings), "method": to_plain(entry)}
    if dataset is not None and seed is not None and (dataset, method, int(seed)) in probe_jobs(settings):
        job["snapshots"] = {"fractions": list(settings.figures.sample_efficiency.fractions)}
    return job


def evaluate_slice(settings: Settings, method: str) -> dict:
    """What an ``evaluate`` job of ``method`` reads: the profile, the day limits, the scenario, the evaluation
    settings, the MLflow experiment (:func:`experiment_slice`), and the method with all its settings."""
    return {"profile": settings.profile, "eval_days": to_plain(settings.run.eval_days),
            "scenario": to_plain(settings.scenario), "evaluation": to_plain(settings.evaluation),
            "mlflow": experiment_slice(settings), "method": to_plain(settings.methods[method])}


def tables_slice(settings: Settings) -> dict:
    """What the ``tables`` job reads: the profile, the tables section, the datasets and the methods' rows."""
    return {"profile": settings.profile, "tables": to_plain(settings.tables), "datasets": list(settings.run.datasets),
            "methods": [to_plain(m.spec) for m in settings.methods.values()]}


def audit_slice(settings: Settings) -> dict:
    """What the audit reads: every setting but the display ones, the selection's, the figures', the resources and
    MLflow's (the audit reads files, never the tracking store)."""
    return to_plain(dataclasses.replace(settings, display=None, selection=None, figures=None, resources=None,
                                        mlflow=None))


def select_slice(settings: Settings) -> dict:
    """What the ``select`` job reads: the profile, the selection, the scenario, the evaluation settings and the
    planner method with all its settings.

    Raises:
        ConfigError: ``selection.planner_method`` is not in ``methods.run``. Only the ``select`` rule needs it, so
            the rule builds this slice when its job is built (every other target runs without it).
    """
    name = settings.selection.planner_method
    if name not in settings.methods:
        raise ConfigError(f"config.yaml: key 'selection.planner_method' is {name!r}, which 'methods.run' does not "
                          f"list (found {', '.join(settings.methods)}); the select target chooses that method's "
                          f"planner values: add {name!r} to 'methods.run', or name a planner method of it in "
                          f"'selection.planner_method'")
    return {"profile": settings.profile, "selection": to_plain(settings.selection),
            "scenario": to_plain(settings.scenario), "evaluation": to_plain(settings.evaluation),
            "method": to_plain(settings.methods[name])}


# ---- the extra runs behind the figures (workflow/rules/extra.smk): scenario and planner variants ----------
VARIANT_KINDS = ("do", "K", "u")
"""``do``: the planner's imagined demand times s (``planner.imagine_scale``, paper Fig. 8 (b)); ``K``: the fleet
size; ``u``: the demand intensity times a factor, applied after calibration (paper Fig. 10)."""


@dataclasses.dataclass(frozen=True)
class Variant:
    """One extra run's one change to the main evaluation, named ``<kind><value>`` (``do0.5``, ``K8``, ``u2``)."""

    kind: str
    """One of :data:`VARIANT_KINDS`."""
    value: float
    """s (``do``), K (``K``, an integer) or the factor of u (``u``)."""

    @property
    def name(self) -> str:
        return f"{self.kind}{self.value:g}"


def parse_variant(name: str) -> Variant:
    """The :class:`Variant` named ``name`` (its :attr:`Variant.name`).

    Raises:
        ValueError: ``name`` is not ``do<s>``, ``K<integer>`` or ``u<factor>`` with a positive number.
    """
    import re

    match = re.fullmatch(r"(do|K|u)(\d+(?:\.\d+)?)", name)
    if not match or float(match[2]) <= 0 or (match[1] == "K" and not match[2].isdigit()):
        raise ValueError(f"extra-run variant {name!r}: expected do<s>, K<integer> or u<factor> with a positive "
                         f"number, e.g. do0.5, K8, u2")
    return Variant(match[1], int(match[2]) if match[1] == "K" else float(match[2]))


def extra_variants(settings: Settings) -> list[Variant]:
    """Every variant the extra runs of ``figures`` need, in order do, K, u. The reference points (s = 1, the
    scenario's own K, u x 1) are the main evaluations and need no run."""
    fig = settings.figures
    out = [Variant("do", float(s)) for s in fig.do_probe.scales if s != 1.0]
    out += [Variant("K", int(k)) for k in fig.scaling.fleet_sizes if k != settings.scenario.n_uavs]
    out += [Variant("u", float(f)) for f in fig.scaling.intensity_scales if f != 1.0]
    return out


def variant_methods(settings: Settings, variant: Variant) -> list[str]:
    """The methods run under ``variant``: those of ``figures.do_probe.methods`` (do) or ``figures.scaling.methods``
    (K, u) that ``methods.run`` evaluates on ``figures.dataset``."""
    fig = settings.figures
    names = fig.do_probe.methods if variant.kind == "do" else fig.scaling.methods
    return fig.present(names, settings)


def extra_jobs(settings: Settings) -> list[tuple[str, str, int]]:
    """Every (variant name, method, seed) extra evaluation on ``figures.dataset``."""
    return [(v.name, m, s) for v in extra_variants(settings) for m in variant_methods(settings, v)
            for s in settings.figures.seeds]


def variant_settings(settings: Settings, variant: Variant, method: str) -> Settings:
    """``settings`` with ``variant``'s change: ``method``'s ``planner.imagine_scale`` = s (do) or the scenario's
    ``n_uavs`` = K (K); the u factor is not a setting of config.yaml (see :func:`variant_train_slice`).

    Raises:
        ConfigError: a do variant of a method whose settings have no ``planner.imagine_scale``.
    """
    if variant.kind == "K":
        return dataclasses.replace(settings, scenario=dataclasses.replace(settings.scenario, n_uavs=int(variant.value)))
    if variant.kind != "do":
        return settings
    m = settings.methods[method]
    planner = getattr(m.options, "planner", None)
    if planner is None or not hasattr(planner, "imagine_scale"):
        raise ConfigError(f"config.yaml: key 'figures.do_probe.methods' names {method!r}, whose settings have no "
                          f"planner.imagine_scale (expected a method of the 'dswm' section, e.g. dswm or dswm_wo_dec)")
    options = dataclasses.replace(m.options, planner=dataclasses.replace(planner, imagine_scale=float(variant.value)))
    return dataclasses.replace(settings, methods={**settings.methods, method: dataclasses.replace(m, options=options)})


def _with_intensity_scale(job: dict, variant: Variant) -> dict:
    """``job`` with ``intensity_scale``, the factor of u applied after calibration, for a u variant."""
    return {**job, "intensity_scale": float(variant.value)} if variant.kind == "u" else job


def variant_train_slice(settings: Settings, method: str, variant: Variant) -> dict:
    """What an ``extra_train`` job of ``method`` under ``variant`` reads: :func:`train_slice` of the variant's
    settings, with ``intensity_scale`` for a u variant. A do variant changes a decision-time setting only, so its
    slice is the main train job's (no training of its own)."""
    return _with_intensity_scale(train_slice(variant_settings(settings, variant, method), method), variant)


def variant_evaluate_slice(settings: Settings, method: str, variant: Variant) -> dict:
    """What an ``extra_evaluate`` job reads: :func:`evaluate_slice` of the variant's settings with the day limits
    of ``figures.eval_days``, and ``intensity_scale`` for a u variant."""
    job = evaluate_slice(variant_settings(settings, variant, method), method)
    job["eval_days"] = to_plain(settings.figures.eval_days)
    return _with_intensity_scale(job, variant)


def variant_retrains(settings: Settings, method: str, variant: Variant) -> bool:
    """True when ``method``'s training source trains again under ``variant`` (its train slice differs from the
    main train job's: K changes the action size, u the reward); False for a method that does not learn."""
    source = settings.methods[method].training_source
    if source is None:
        return False
    return variant_train_slice(settings, source, variant) != train_slice(settings, source)


def scale_intensity(scenario: Scenario, factor: float) -> Scenario:
    """``scenario`` with u times ``factor`` (a u variant's ``intensity_scale``); u must be a number already
    (:func:`calibrated_scenario` first).

    Raises:
        ValueError: u is still ``calibrate``.
    """
    if factor == 1.0:
        return scenario
    if scenario.calibrates:
        raise ValueError(f"scenario.demand_intensity is {CALIBRATE!r}: resolve u from the calibrate rule's record "
                         f"(calibrated_scenario) before multiplying it by {factor}")
    return dataclasses.replace(scenario, demand_intensity=float(scenario.demand_intensity) * float(factor))


# ---- the sample-efficiency probe (workflow/rules/probes.smk) ------------------------------------------------
def probed_methods(settings: Settings) -> list[str]:
    """The methods of ``figures.sample_efficiency.methods`` the probe runs: those ``methods.run`` evaluates on
    ``figures.dataset`` that the ``train`` rule fits (their own training source; a method that evaluates another's
    model, e.g. ``dswm_wo_unc``, is not probed apart)."""
    fig = settings.figures
    if fig is None:
        return []
    trained = settings.trained()
    return [m for m in fig.present(fig.sample_efficiency.methods, settings) if m in trained]


def probe_jobs(settings: Settings) -> list[tuple[str, str, int]]:
    """Every (dataset, method, seed) whose train job snapshots its model and whose snapshots the probe evaluates:
    ``figures.dataset`` x :func:`probed_methods` x ``figures.seeds``."""
    if settings.figures is None:
        return []
    return [(settings.figures.dataset, m, int(s)) for m in probed_methods(settings) for s in settings.figures.seeds]


def probe_slice(settings: Settings, method: str) -> dict:
    """What a ``probe`` job of ``method`` reads: :func:`evaluate_slice` less the day limits (the probe runs one
    fixed day, the first ID test day): the method with all its settings, as its evaluation."""
    return {k: v for k, v in evaluate_slice(settings, method).items() if k != "eval_days"}


def figures_slice(settings: Settings) -> dict:
    """What a figure job of the results reads: the tables' slice (profile, tables, datasets, the methods' rows),
    the MLflow experiment (the runs its figure is attached to; :func:`experiment_slice`) and the ``figures``
    section."""
    return {**tables_slice(settings), "mlflow": experiment_slice(settings), "figures": to_plain(settings.figures)}
