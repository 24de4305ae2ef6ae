"""config.yaml resolved into :class:`Settings`: the schema check, the profile, every section typed, then the
cross-key checks the schema cannot make (a profile's datasets and seeds, the methods' names, the tables' and
figures' datasets, the raw files on disk).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

from dswm.config import ConfigError, ConfigSources, build
from dswm.methods import registry
from dswm.settings.model import MethodSettings, Settings
from dswm.settings.schema import SCHEMA, coerce_cli_strings, load_schema, validate_config
from dswm.settings.sections import (CalibrationSettings, Display, EvaluationSettings, MlflowSettings, RunSettings,
                                    SelectionSettings, TablesSettings, figures_settings, resource_settings)
from dswm.settings.variants import check_room_fill
from dswm.sim.scenario import Scenario
from prep.config import DATASETS, DatasetsConfig


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
    check_room_fill(settings)
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
