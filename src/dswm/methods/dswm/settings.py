"""DSWM's typed settings: config.yaml's ``dswm`` section resolved for one method under one profile.

``dswm`` (Algorithm 1), its ablations ``dswm_wo_unc`` and ``dswm_wo_dec``, ``dswm_plus`` and the planners that share
DSWM+'s settings (``dswm_plus_persist``, ``perfect``) are configurations of the same code: each method's overrides
(``dswm.methods.<method>``) and the profile's planner reductions (``dswm.budgets.<profile>.planner``) are
merged over the base sections, and the result is built by the project's one typed builder. The planner's BCD
proposal runs the project's one search (config.yaml ``search``), passed in whole.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Mapping

from dswm.config import ConfigError, build, merge, setting, with_budget
from dswm.methods.dswm.planner import PlannerConfig
from dswm.methods.search import SearchSettings
from dswm.methods.dswm.training import TrainConfig
from dswm.methods.dswm.world_model import WorldModelConfig


@dataclasses.dataclass(frozen=True, kw_only=True)
class DSWMBudget:
    """What a profile sets of DSWM (config.yaml ``dswm.budgets.<profile>``): the training budget, and the training
    and planner keys it changes (merged over ``dswm.training`` and ``dswm.planner``, before the method's
    overrides)."""

    transitions: int = setting("count")
    """Pre-collected training transitions."""
    steps: int = setting("count")
    """Gradient steps."""
    training: dict[str, Any] = setting(ref="dswm_training_partial")
    """Some keys of ``dswm.training`` (the schema's ``$defs/dswm_training_partial``; checked as the merged
    training settings)."""
    planner: dict[str, Any] = setting(ref="dswm_planner_partial")
    """Some keys of ``dswm.planner`` (the schema's ``$defs/dswm_planner_partial``; checked as the merged planner)."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class DSWMSettings:
    """Resolved settings of one DSWM method under one profile."""

    device: str
    """Torch device of the world model, its training and planning."""
    world_model: WorldModelConfig
    """config.yaml ``dswm.world_model`` (its RSSM keys under ``rssm``)."""
    training: TrainConfig
    """config.yaml ``dswm.training`` (optimization and pre-collection)."""
    transitions: int
    """Pre-collected training transitions (``dswm.budgets.<profile>.transitions``)."""
    steps: int
    """Gradient steps (``dswm.budgets.<profile>.steps``)."""
    planner: PlannerConfig | None
    """The decision-time planner; None in the part a train job receives (training does not plan)."""


def resolve(dswm: Mapping[str, Any], *, method: str, profile: str, search: Mapping[str, Any]) -> DSWMSettings:
    """Resolve config.yaml's ``dswm`` section for ``method`` under ``profile``.

    Args:
        dswm: the ``dswm`` section; method: a name under ``dswm.methods``; profile: the budget profile;
        search: config.yaml's ``search`` section (the project's one BCD search).

    Raises:
        ConfigError: the method or profile has no entry, a merged section has an unknown, missing or mistyped
            key, or the merged planner's ``n_elites`` is not in [1, n_samples] (the one cross-key check the
            schema cannot make: it sees each section, not the merged planner).
    """
    if method not in dswm["methods"]:
        raise ConfigError(f"config.yaml: key 'dswm.methods' has no entry {method!r} (found {sorted(dswm['methods'])})")
    budgeted, _ = with_budget(dswm, profile, "dswm", required=True)  # transitions, steps, training and planner keys
    budget = build(DSWMBudget, dswm["budgets"][profile], f"dswm.budgets.{profile}")
    over = dswm["methods"].get(method) or {}
    planner = build(PlannerConfig, merge(budgeted["planner"], over.get("planner")),
                    "dswm.planner", search=build(SearchSettings, search, "search"))
    if not 1 <= planner.n_elites <= planner.n_samples:
        raise ConfigError(f"config.yaml: method {method!r}: key 'dswm.planner.n_elites' must lie in [1, n_samples] "
                          f"(after the 'dswm.budgets.{profile}.planner' and 'dswm.methods.{method}.planner' "
                          f"overrides); found n_elites={planner.n_elites}, n_samples={planner.n_samples}")
    return DSWMSettings(
        device=str(dswm["device"]),
        world_model=WorldModelConfig.from_flat(merge(dswm["world_model"], over.get("world_model")),
                                               "dswm.world_model"),
        training=build(TrainConfig, merge(budgeted["training"], over.get("training")), "dswm.training"),
        transitions=budget.transitions, steps=budget.steps, planner=planner)
