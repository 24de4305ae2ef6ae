"""The registry of methods by name: the built-in ones in :data:`BUILTIN`, a user's own through
``methods.user.<name>.class: "package.module:ClassName"`` in config.yaml.
"""
from __future__ import annotations

import dataclasses
import importlib
from typing import Any, Mapping

from dswm.config import ConfigError, stable_hash, to_plain
from dswm.methods.base import Controller


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
    _spec("dswm", "dswm.methods.dswm.agent:DSWMController", "DSWM (Algorithm 1)", "world model"),
    _spec("dswm_wo_unc", "dswm.methods.dswm.agent:DSWMController", "w/o unc", "ablation"),
    _spec("dswm_wo_dec", "dswm.methods.dswm.agent:DSWMController", "w/o dec", "ablation"),
    _spec("dswm_plus", "dswm.methods.dswm.agent:DSWMController", "DSWM+ (this project)", "world model"),
    _spec("dswm_plus_persist", "dswm.methods.dswm.agent:PersistenceController", "DSWM+ on persistence (probe)",
          "ablation"),
    _spec("greedy", "dswm.methods.classical:GreedyController", "Greedy (BCD)", "model-free"),
    _spec("static", "dswm.methods.classical:StaticController", "Static (K-means)", "deployment"),
    _spec("ins_woa", "dswm.methods.ins_woa:InsWoaController", "INS-WOA", "optimization"),
    _spec("jtoratc", "dswm.methods.jtoratc:JTORATCController", "JTORATC", "BCD optim."),
    _spec("ppo", "dswm.methods.rl.sb3:PPOController", "PPO", "model-free RL"),
    _spec("sac", "dswm.methods.rl.sb3:SACController", "SAC", "model-free RL"),
    _spec("maddpg", "dswm.methods.maddpg:MADDPGController", "MADDPG", "MARL"),
    _spec("ga_matr", "dswm.methods.ga_matr:GAMATRController", "GA-MATR", "MARL"),
    _spec("emorl_tcto", "dswm.methods.emorl_tcto:EMORLTCTOController", "EMORL-TCTO", "multi-obj. RL"),
    _spec("hrl_tpra", "dswm.methods.hrl_tpra:HRLTPRAController", "HRL-TPRA", "hier. RL"),
    _spec("tdmpc", "dswm.methods.tdmpc:TDMPCController", "TD-MPC", "model-based"),
    _spec("oracle", "dswm.methods.classical:OracleController", "Oracle (clairvoyant)", "upper bound"),
    _spec("perfect", "dswm.methods.dswm.agent:PerfectForecastController", "Perfect forecast (clairvoyant)",
          "upper bound"),
    _spec("ceiling", "dswm.methods.ceiling:CeilingController", "Ceiling (clairvoyant)", "upper bound"),
]}
"""Built-in methods (docs/PROTOCOL.md §5): the paper's 14, this project's DSWM+ and its probe, the three upper bounds
(the oracle, the perfect forecast and the per-slot ceiling)."""


def lookup(name: str, methods: Mapping[str, Any]) -> tuple[MethodSpec, type[Controller]]:
    """The MethodSpec and the class of ``name``: a user method of the ``methods`` section, else a built-in one.

    Raises:
        ConfigError: ``name`` is neither registered nor defined under ``methods.user``, or its class cannot be
            imported or is no Controller.
    """
    user = methods.get("user", {}).get(name)
    if user is not None:
        cls = load_class(user["class"], key=f"methods.user.{name}.class")
        return MethodSpec(name=name, target=user["class"], label=getattr(cls, "label", name),
                          table_class=getattr(cls, "table_class", "user")), cls
    if name in BUILTIN:
        return BUILTIN[name], load_class(BUILTIN[name].target, key="methods.run")
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
                          f"dswm.methods.base.Controller (found {cls!r})")
    return cls


def build(name: str, *, target: str, options: Any, seed: int, device: str) -> Controller:
    """Construct method ``name`` (class path ``target``) with its typed settings for a job with ``seed``."""
    return load_class(target, key=f"methods.{name}")(name=name, seed=seed, device=device, options=options)


def training_identity(cls: type[Controller], options: Any) -> str:
    """Hash of the class and of what its :meth:`~Controller.fit` reads: equal identities train the same model."""
    return stable_hash({"class": f"{cls.__module__}:{cls.__qualname__}",
                        "training": to_plain(cls.training_settings(options))})


def training_sources(learning: Mapping[str, tuple[type[Controller], Any]]) -> dict[str, str]:
    """The method whose trained model each learning method evaluates.

    A method's training source is the first method (in ``methods.run`` order) of a class that
    ``shares_training`` with an equal :func:`training_identity`: such methods differ only at decision time, so
    the ``train`` rule fits the source alone and every method mapped to it loads the source's ``model.pt``.

    Args:
        learning: {learning method: (class, typed settings)} in run order.

    Returns:
        {learning method: training source} in run order.
    """
    first: dict[str, str] = {}
    return {name: first.setdefault(training_identity(cls, options), name) if cls.shares_training else name
            for name, (cls, options) in learning.items()}
