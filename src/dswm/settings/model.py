"""The run's settings as one typed object: :class:`Settings` (every section under the selected profile) and
:class:`MethodSettings` (one method of ``methods.run`` with its class's typed settings), and the questions the rules
ask of them.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Mapping, Sequence

from dswm.config import build, stable_hash, to_plain
from dswm.methods import registry
from dswm.settings.sections import (CalibrationSettings, Display, EvaluationSettings, FiguresSettings, MlflowSettings,
                                    ResourceSettings, RunSettings, SelectionSettings, TablesSettings)
from dswm.sim.scenario import Scenario
from prep.config import DatasetsConfig


@dataclasses.dataclass(frozen=True, kw_only=True)
class MethodSettings:
    """One method of ``methods.run``: its registration and its typed settings."""

    name: str
    """The method's name in ``methods.run`` (a registered or user method)."""
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
    """The selected profile (config.yaml ``profile``: demo, smoke or paper)."""
    run: RunSettings
    """The selected ``profiles.<profile>`` entry: datasets, seeds and day limits."""
    scenario: Scenario
    """config.yaml ``scenario``: the environment every job simulates (u maybe ``calibrate``)."""
    evaluation: EvaluationSettings
    """config.yaml ``evaluation`` less its display setting."""
    methods: dict[str, MethodSettings]
    """The methods of ``methods.run``, in that order (table order within a table class)."""
    calibration: CalibrationSettings
    """config.yaml ``calibration``: how the ``calibrate`` rule finds u."""
    selection: SelectionSettings | None
    """None in the audit's slice (the audit reads no selection)."""
    mlflow: MlflowSettings | None
    """None in the audit's slice (where a run is logged changes no result the audit checks)."""
    tables: TablesSettings
    """config.yaml ``tables``: how the tables are laid out."""
    figures: FiguresSettings | None = None
    """None in a job's slice that reads no figure setting (the audit's)."""
    resources: ResourceSettings | None = None
    """What each rule's jobs ask a cluster for; None in the audit's slice (where a job runs changes no result)."""
    datasets: DatasetsConfig
    """config.yaml ``datasets``: each dataset's preparation and the common settings."""
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


def evaluated_as(settings: Settings, method: str) -> list[str]:
    """The methods whose evaluations load the model that ``method`` trains (an MLflow tag of its train run)."""
    return [m for m, src in settings.training_sources().items() if src == method] or [method]


REUSED_FILES = ("days", "trajectory", "record")
"""The files of a reused evaluation: an evaluate or extra_evaluate job's outputs of these names at the first seed are
its Snakemake inputs ``reuse_<name>`` (workflow/rules/common.smk ``reused_evaluation``)."""


def reused_seed(settings: Settings, dataset: str, method: str, seed: int,
                seeds: Sequence[int] | None = None) -> int | None:
    """The seed whose evaluation of ``method`` on ``dataset`` the evaluate job of ``seed`` reuses, or None when the
    job evaluates on its own.

    With ``evaluation.reuse_seed_independent``, a method whose class says the seed does not change its result
    (``Controller.deterministic``; no learning method) is evaluated at the first of ``seeds`` only (None: the
    profile's seeds of ``dataset``; an extra run's: ``figure_seeds``), and every other seed reuses that evaluation.
    """
    if not settings.evaluation.reuse_seed_independent:
        return None
    spec = settings.methods[method]
    first = (settings.seeds(dataset) if seeds is None else list(seeds))[0]
    if spec.learns or seed == first or not spec.controller_class.deterministic:
        return None
    return first


def needs_gpu(settings: Settings, method: str | None) -> bool:
    """True when a job of ``method`` (None: a job without a method) runs torch on a CUDA device: its own ``device``
    setting (the DSWM methods' ``dswm.device``) or ``evaluation.device`` (the environment's) says cuda."""
    devices = [settings.evaluation.device]
    if method is not None and method in settings.methods:
        devices.append(getattr(settings.methods[method].options, "device", None) or "cpu")
    return any(str(d).startswith("cuda") for d in devices)
