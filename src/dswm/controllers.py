"""The controller interface every method implements, and the registry of methods by name.

A controller sees one observation per slot and answers an action ``(K, 3)`` in [-1, 1]: (dx, dy) as a
fraction of D_max and the bandwidth logit of each UAV. Before each evaluated day it receives a
:class:`DayContext`; only a controller that declares ``clairvoyant = True`` (the oracle) gets the day's true
demand in it. Learning methods declare ``learns = True`` and implement :meth:`Controller.fit` on a core built
from the TRAINING days only, plus :meth:`save`/:meth:`load`; methods whose training is identical
(:meth:`Controller.training_identity`) share one trained model (:func:`training_sources`).

Methods are looked up by name: the built-in ones in :data:`BUILTIN`, a user's own through
``methods.user.<name>.class: "package.module:ClassName"`` in config.yaml.
"""
from __future__ import annotations

import dataclasses
import importlib
from typing import Any, ClassVar, Mapping, Sequence

import numpy as np

from dswm.config import ConfigError


@dataclasses.dataclass(frozen=True, kw_only=True)
class DayContext:
    """What a controller is told at the start of an evaluated (or training) day."""

    dataset: str
    """Dataset name."""
    day: int
    """Tensor day index (position in meta["days"])."""
    label: str
    """Day label (ISO date, or "d56" for YJMob)."""
    split: str
    """"id", "ood" or "train"."""
    grid: Any
    """The dataset grid (rows, cols, cell_m)."""
    scenario: Any
    """The Scenario constants."""
    geometry: Any
    """Area size and station positions (dswm.fleet.Geometry)."""
    cells: Any
    """(G, 2) cell centres in metres, float32 tensor."""
    init_pos: np.ndarray
    """(K, 2) initial (and static) positions in metres."""
    device: str = "cpu"
    """Torch device of the evaluation."""
    demand: np.ndarray | None = None
    """(T, R, C) the day's TRUE demand; set only for clairvoyant controllers."""


class Controller:
    """Base class of every method. Constructors are keyword-only.

    Attributes:
        name: the registered method name.
        clairvoyant: True only for the oracle; it alone receives ``DayContext.demand``.
        learns: True for methods trained by the ``train`` rule before evaluation.
        batched: True if :meth:`reset_batch`/:meth:`act_batch` step several days at once.
        deterministic: True if the seed does not change the result (static, greedy, oracle).
    """

    clairvoyant: ClassVar[bool] = False
    learns: ClassVar[bool] = False
    batched: ClassVar[bool] = False
    deterministic: ClassVar[bool] = False

    def __init__(self, *, name: str, seed: int = 0, device: str = "cpu"):
        self.name = name
        self.seed = seed
        self.device = device

    @classmethod
    def from_config(cls, *, name: str, config: Mapping[str, Any], seed: int) -> "Controller":
        """Build from the resolved config; the default passes ``methods.<name>`` or user options as kwargs.

        Args:
            name: registered method name.
            config: the resolved config (runconfig.resolve).
            seed: the job's seed.
        """
        options = dict(config["methods"].get(name, {}) or {})
        user = config["methods"].get("user", {}).get(name)
        if user is not None:
            options = dict(user.get("options", {}))
        return cls(name=name, seed=seed, device=config["evaluation"]["device"], **options)

    @classmethod
    def budget_from_config(cls, *, name: str, config: Mapping[str, Any]) -> dict:
        """Training budget of this method under the selected profile (``config["profile"]``); {} if none."""
        return {}

    @classmethod
    def training_identity(cls, *, name: str, config: Mapping[str, Any]) -> str | None:
        """Hash of everything that shapes the training of method ``name`` under ``config``, or None.

        Methods of one class whose identities are equal train the same model on a (dataset, seed), so they share
        one ``train`` job (:func:`training_sources`). A learning controller opts in by returning a hash of every
        setting :meth:`fit` reads (budget included; the seed is the job's and is not part of it); None, the
        default, means the method always trains alone.
        """
        return None

    def fit(self, train_core, *, budget: Mapping[str, Any], run_dir) -> dict:
        """Train on a core over the TRAINING days only; return the training manifest (docs/ARCHITECTURE.md).

        A manifest may carry ``history``: {metric name: list of values per step}; the train rule logs it to
        MLflow in batches and keeps it out of train_manifest.json.
        """
        raise NotImplementedError(f"method {self.name!r} does not learn")

    def reset(self, ctx: DayContext) -> None:
        """Prepare for one day."""
        raise NotImplementedError

    def act(self, obs: Mapping[str, Any]) -> np.ndarray:
        """One action for one observation.

        Args:
            obs: {"demand": (7, R, C), "fleet": (K, 7), "time": (2,)}.

        Returns:
            (K, 3) float array in [-1, 1].
        """
        raise NotImplementedError

    def reset_batch(self, ctxs: Sequence[DayContext]) -> None:
        """Prepare for B days stepped together (only when ``batched``)."""
        raise NotImplementedError(f"method {self.name!r} is not batched")

    def act_batch(self, obs: Mapping[str, Any]) -> np.ndarray:
        """Actions ``(B, K, 3)`` for a batch of observations with a leading axis B (only when ``batched``)."""
        raise NotImplementedError(f"method {self.name!r} is not batched")

    def save(self, path) -> None:
        """Write everything needed to act again (weights, normalizer stats, RNG state)."""
        raise NotImplementedError(f"method {self.name!r} has no state to save")

    def load(self, path) -> None:
        """Read what :meth:`save` wrote."""
        raise NotImplementedError(f"method {self.name!r} has no state to load")


@dataclasses.dataclass(frozen=True, kw_only=True)
class MethodSpec:
    """A registered method: its class and how the tables name and group it."""

    name: str
    target: str
    """Importable class path "package.module:ClassName"."""
    label: str
    """Row label in the tables."""
    table_class: str
    """Class column of Table III (e.g. "deployment")."""


def _spec(name: str, target: str, label: str, table_class: str) -> MethodSpec:
    return MethodSpec(name=name, target=target, label=label, table_class=table_class)


BUILTIN: dict[str, MethodSpec] = {s.name: s for s in [
    _spec("dswm", "dswm.agent:DSWMController", "DSWM (ours)", "world model"),
    _spec("dswm_wo_unc", "dswm.agent:DSWMController", "w/o unc", "ablation"),
    _spec("dswm_wo_dec", "dswm.agent:DSWMController", "w/o dec", "ablation"),
    _spec("greedy", "dswm.baselines:GreedyController", "Greedy (BCD)", "model-free"),
    _spec("static", "dswm.baselines:StaticController", "Static (K-means)", "deployment"),
    _spec("oracle", "dswm.baselines:OracleController", "Oracle (clairvoyant)", "upper bound"),
]}
"""Built-in methods (SPEC section 5). The other paper baselines are added here as they are implemented."""


def spec(name: str, config: Mapping[str, Any]) -> MethodSpec:
    """The MethodSpec of ``name``: a user method from config, else a built-in one.

    Raises:
        ConfigError: ``name`` is neither registered nor defined under ``methods.user``.
    """
    user = config["methods"].get("user", {}).get(name)
    if user is not None:
        cls = load_class(user["class"], key=f"methods.user.{name}.class")
        return MethodSpec(name=name, target=user["class"], label=getattr(cls, "label", name),
                          table_class=getattr(cls, "table_class", "user"))
    if name in BUILTIN:
        return BUILTIN[name]
    known = ", ".join(sorted(BUILTIN))
    raise ConfigError(f"config.yaml: key 'methods.run' names {name!r}, which is not a registered method "
                      f"(expected one of {known}, or a user method defined under 'methods.user.{name}' "
                      f"with class: 'package.module:ClassName')")


def load_class(target: str, *, key: str = "methods") -> type[Controller]:
    """Import ``"package.module:ClassName"`` and check it is a Controller subclass.

    Args:
        target: the class path.
        key: the config key that names it (for messages).
    """
    module_name, _, class_name = target.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ImportError as err:
        raise ConfigError(f"config.yaml: key '{key}': cannot import module {module_name!r} of {target!r} "
                          f"({err}); expected an importable 'package.module:ClassName'") from err
    cls = getattr(module, class_name, None)
    if not (isinstance(cls, type) and issubclass(cls, Controller)):
        raise ConfigError(f"config.yaml: key '{key}': {target!r} is not a subclass of "
                          f"dswm.controllers.Controller (found {cls!r})")
    return cls


def controller_class(name: str, config: Mapping[str, Any]) -> type[Controller]:
    """The class of method ``name``."""
    s = spec(name, config)
    return load_class(s.target, key=f"methods.user.{name}.class" if name not in BUILTIN else "methods.run")


def build(name: str, *, config: Mapping[str, Any], seed: int) -> Controller:
    """Construct method ``name`` for a job with ``seed`` from the resolved config."""
    return controller_class(name, config).from_config(name=name, config=config, seed=seed)


def check_methods(config: Mapping[str, Any]) -> dict[str, type[Controller]]:
    """Resolve every method of ``methods.run``; raise ConfigError naming the first bad one.

    Returns:
        {name: class} in run order.
    """
    return {name: controller_class(name, config) for name in config["methods"]["run"]}


def training_sources(config: Mapping[str, Any]) -> dict[str, str]:
    """The method whose trained model each learning method of ``methods.run`` evaluates.

    A method's training source is the first method in ``methods.run`` order of the same class with an equal
    :meth:`Controller.training_identity`: such methods differ only at decision time, so the ``train`` rule fits
    the source alone and every method mapped to it loads the source's ``model.pt``. A method whose identity is
    None is its own source.

    Args:
        config: the resolved config (runconfig.resolve).

    Returns:
        {learning method: training source} in run order; methods that do not learn are absent.

    Raises:
        ConfigError: a method's identity cannot be computed from config (the message names the method).
    """
    first: dict[tuple[str, str], str] = {}
    out: dict[str, str] = {}
    for name, cls in check_methods(config).items():
        if not cls.learns:
            continue
        try:
            identity = cls.training_identity(name=name, config=config)
        except (KeyError, ValueError) as err:
            raise ConfigError(f"config.yaml: method {name!r} of 'methods.run': its settings cannot be resolved "
                              f"({err})") from err
        key = None if identity is None else (f"{cls.__module__}:{cls.__qualname__}", str(identity))
        out[name] = name if key is None else first.setdefault(key, name)
    return out


def training_rerun_params(config: Mapping[str, Any], method: str) -> dict:
    """What a ``train`` job of ``method`` depends on besides its input files (Snakemake reruns it on a change).

    The profile, the scenario, the method's own options and its training identity; for a learning method that
    declares no identity, the whole ``dswm`` section instead (the safe side). Planner settings, ablation
    overrides that only act at decision time and the evaluation options are not part of it, so changing them
    reruns evaluations, never training.

    Args:
        config: the resolved config (runconfig.resolve); method: a learning method of ``methods.run``.
    """
    cls = check_methods(config)[method]
    identity = cls.training_identity(name=method, config=config)
    methods = config["methods"]
    return {
        "profile": config["profile"],
        "scenario": config["scenario"],
        "method": {k: v for k, v in methods.items() if k == method},
        "user": methods["user"].get(method, {}),
        "training": identity if identity is not None else config.get("dswm", {}),
    }
