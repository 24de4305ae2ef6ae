"""The controller interface every method implements.

A controller sees one observation per slot and answers an action ``(K, 3)`` in [-1, 1]: (dx, dy) as a
fraction of D_max and the bandwidth logit of each UAV. Before each evaluated day it receives a
:class:`DayContext`; only a controller that declares ``clairvoyant = True`` (the bounds) gets the day's true
demand in it; a per-slot bound (``places = True``, the ceiling) places the fleet each slot instead of acting.
Learning methods declare ``learns = True`` and implement :meth:`Controller.fit` on a core built from the TRAINING
days only, plus :meth:`save`/:meth:`load`; methods whose training is identical
(:meth:`Controller.training_settings`) share one trained model (``dswm.methods.registry.training_sources``).
A method's settings are one typed section, :attr:`Controller.options_type`, built by ``dswm.config.build``.
"""
from __future__ import annotations

import dataclasses
import hashlib
from typing import Any, ClassVar, Mapping, Sequence

import numpy as np

from dswm.config import ConfigError, build, stable_hash, with_budget


def training_inputs_hash(core, day_ids=None) -> str:
    """Hash of what a training run reads besides its settings: the training-day demand tensor, its day ids (tensor
    day of each of ``core``'s days; ``core.day_ids`` when None) and labels, the grid and the scenario of ``core``
    (a FleetCore of TRAINING days). A learning method's checkpoint resumes only a run with the same hash."""
    if day_ids is None:
        day_ids = getattr(core, "day_ids", range(core.n_days))
    demand = hashlib.sha256(np.ascontiguousarray(core.demand.detach().cpu().numpy()).tobytes()).hexdigest()
    return stable_hash({"demand_sha256": demand, "day_ids": np.asarray(day_ids, dtype=np.int64).tolist(),
                        "day_labels": list(core.day_labels), "grid": dataclasses.asdict(core.grid),
                        "scenario": dataclasses.asdict(core.scenario)})


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
    """Area size and station positions (dswm.sim.fleet.Geometry)."""
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
        clairvoyant: True only for the bounds (oracle, perfect, ceiling); they alone receive ``DayContext.demand``.
        learns: True for methods trained by the ``train`` rule before evaluation.
        batched: True if :meth:`reset_batch`/:meth:`act_batch` step several days at once.
        deterministic: True if the result is a function of the inputs alone: neither the seed nor the clock changes
            it (static, greedy, oracle, the ceiling); such a method is evaluated once per dataset
            (``evaluation.reuse_seed_independent``).
        places: True only for a per-slot bound (the ceiling): it flies no fleet, it places it (:meth:`place_batch`).
    """

    clairvoyant: ClassVar[bool] = False
    learns: ClassVar[bool] = False
    batched: ClassVar[bool] = False
    deterministic: ClassVar[bool] = False
    places: ClassVar[bool] = False
    """A per-slot bound, not a controller: the evaluation asks :meth:`place_batch` for each slot's placement of the
    whole fleet and serves it with every UAV available and no motion limit (``FleetCore.place``), instead of
    stepping the fleet with :meth:`act_batch`'s action."""

    shares_training: ClassVar[bool] = False
    """Methods of this class whose :meth:`training_settings` are equal share one trained model; off by default,
    so a method trains alone unless its class says which of its settings shape training."""
    options_type: ClassVar[type | None] = None
    """The method's typed settings: a keyword-only dataclass built by ``dswm.config.build`` from
    ``methods.<name>`` (or a user method's ``options``); None for a method without settings."""

    def __init__(self, *, name: str, seed: int = 0, device: str = "cpu", options: Any = None):
        self.name = name
        self.seed = seed
        self.device = device
        self.options = options

    @classmethod
    def options_from_config(cls, *, name: str, config: Mapping[str, Any], profile: str) -> Any:
        """The typed settings of method ``name`` from the validated config.yaml mapping (parse time only).

        The default builds :attr:`options_type` from ``methods.user.<name>.options`` for a user method, else from
        ``methods.<name>``; a class without ``options_type`` gets None. A built-in section may hold ``budgets``:
        {profile: {key: value}}, the selected profile's entry overriding the section's keys (a smaller demo budget
        is a profile of the same settings). A class whose settings live elsewhere (DSWM: the ``dswm`` section,
        merged for the method and the profile) overrides this.
        """
        user = config["methods"].get("user", {}).get(name)
        key = f"methods.user.{name}.options" if user is not None else f"methods.{name}"
        section = dict(user.get("options", {})) if user is not None else config["methods"].get(name)
        if user is None and isinstance(section, Mapping) and "budgets" in section:
            section, key = with_budget(section, profile, key)
        return cls.options_from_plain(name=name, data=section, where=key)

    @classmethod
    def options_from_plain(cls, *, name: str, data: Any, where: str | None = None) -> Any:
        """The typed settings back from their plain form (a job's settings slice, ``dswm.config.to_plain``)."""
        if cls.options_type is None:
            if data:
                raise ConfigError(f"config key {where or 'methods.' + name}: method {name!r} declares no "
                                  f"options_type (a keyword-only dataclass of its settings); found {data!r}")
            return None
        return build(cls.options_type, data if data is not None else {}, where or f"methods.{name}")

    @classmethod
    def training_settings(cls, options: Any) -> Any:
        """The part of ``options`` that :meth:`fit` reads (the default: all of it).

        A train job receives only this part, so settings that act at decision time only do not retrain. Methods of
        one class whose training settings are equal train the same model on a (dataset, seed) and share one
        ``train`` job (``dswm.methods.registry.training_sources``).
        """
        return options

    def search_settings(self) -> Any:
        """The per-slot block-coordinate-descent search this method runs (a ``dswm.methods.search.SearchSettings``),
        or None when it runs none. Every BCD of a run must use the one ``search`` section of config.yaml; each result
        file records this value and the audit compares it across methods (docs/AUDIT.md)."""
        return None

    def fit(self, train_core, *, run_dir, snapshots=None) -> dict:
        """Train on a core over the TRAINING days only; return the training manifest (docs/ARCHITECTURE.md).

        A manifest may carry ``history``: {metric name: list of values per step}; the train rule logs it to
        MLflow in batches and keeps it out of train_manifest.json. ``snapshots`` (a
        ``dswm.methods.snapshots.Snapshots``, or None) asks for model snapshots at fractions of the budget: the fit
        loop claims its checkpoint with it first, then calls its ``step`` after every unit of the budget.
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

    def place_batch(self, obs: Mapping[str, Any]) -> tuple[np.ndarray, np.ndarray]:
        """A per-slot bound's placement for the next slot of B days (only when ``places``): positions (B, K, 2) in
        metres and bandwidth logits (B, K) in [-1, 1]."""
        raise NotImplementedError(f"method {self.name!r} places no fleet")

    def day_stats(self) -> list[dict[str, float]]:
        """Extra numbers of the days of the last :meth:`reset` / :meth:`reset_batch`, one mapping per day in that
        order, asked for after the days' last action. The evaluation writes each key as a column
        ``stat_<key>`` of days.parquet (``dswm.protocol.evaluation.STAT_PREFIX``); the default reports none.
        """
        return []

    def save(self, path) -> None:
        """Write everything needed to act again (weights, normalizer stats, RNG state)."""
        raise NotImplementedError(f"method {self.name!r} has no state to save")

    def load(self, path) -> None:
        """Read what :meth:`save` wrote."""
        raise NotImplementedError(f"method {self.name!r} has no state to load")
