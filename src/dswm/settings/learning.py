"""The learning curves (workflow/rules/learning.smk, config.yaml ``learning``): which learners run, at what cap, with
which snapshots, scored on which days; and the slices of their jobs.

Each learner of :func:`learning_methods` trains ONE run on ``learning.dataset`` with seed ``learning.seed``, its
budget the method's own under the profile with ``learning.caps.<method>`` merged over its options (the cap), on the
training days less the last ``learning.validation_days`` (``dswm.protocol.learning.learning_days``). The run
snapshots its model before the first update and at every fraction of ``learning.ladder``; every snapshot, and each
method of ``learning.references`` (no training), is scored on those validation days. The section is kept out of
:class:`~dswm.settings.model.Settings`, so no slice of the tables' jobs changes with it.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Mapping

from dswm.config import ConfigError, build, merge, to_plain, with_budget
from dswm.settings.model import Settings
from dswm.settings.sections import start_priority
from dswm.settings.slices import evaluate_slice, train_slice


@dataclasses.dataclass(frozen=True, kw_only=True)
class LearningSettings:
    """config.yaml ``learning`` merged with ``learning.budgets.<profile>``."""

    dataset: str
    """The dataset the learners train on (one the profile prepares)."""
    seed: int
    """The seed of the one run per learner."""
    validation_days: int
    """The last this many TRAINING days are held out of training and score every snapshot."""
    ladder: tuple[float, ...]
    """The budget fractions snapshotted, in (0, 1], 1 the cap; the untrained model (fraction 0) is always added."""
    methods: tuple[str, ...]
    """The learners drawn (those of ``methods.run`` that the ``train`` rule fits)."""
    references: tuple[str, ...]
    """Methods without training scored on the same days (the figure's horizontal lines)."""
    caps: dict[str, Any]
    """{method: options merged over its profile's options}: the budget of its one run (none: its own budget)."""
    start_order: tuple[str, ...]
    """Learners whose jobs start first, in this order (the longest runs first, so that the cores stay busy to the
    end); the others after them. Scheduling only: no job's settings or results change with it."""


def learning_settings(config: Mapping[str, Any], profile: str) -> LearningSettings:
    """``learning`` of a validated config with ``learning.budgets.<profile>`` merged in.

    Raises:
        ConfigError: a ladder without the cap (1) or with a repeated fraction.
    """
    out = build(LearningSettings, *with_budget(config["learning"], profile, "learning"))
    ladder = sorted(out.ladder)
    if len(set(ladder)) != len(ladder) or not ladder or ladder[-1] != 1.0 or ladder[0] <= 0.0:
        raise ConfigError(f"config.yaml: key 'learning.ladder' (profile {profile!r}): expected distinct fractions of "
                          f"the cap in (0, 1] ending at 1 (the cap itself), found {list(out.ladder)}")
    return dataclasses.replace(out, ladder=tuple(ladder))


def learning_methods(settings: Settings, learning: LearningSettings) -> list[str]:
    """The learners of ``learning.methods`` that run: those ``methods.run`` evaluates on ``learning.dataset`` and the
    ``train`` rule fits (a method evaluating another's model, e.g. ``dswm_wo_unc``, is not drawn apart)."""
    trained = settings.trained()
    return [m for m in learning.methods if m in trained and m in settings.methods_on(learning.dataset)]


def learning_priority(learning: LearningSettings, learners: list[str], method: str) -> int:
    """The Snakemake ``priority`` of ``method``'s learning jobs: ``len(order) - i`` for the i-th drawn learner of
    ``learning.start_order`` (the first the highest), 0 for every other method (higher starts first)."""
    return start_priority([m for m in learning.start_order if m in learners], method)


def learning_references(settings: Settings, learning: LearningSettings) -> list[str]:
    """The methods of ``learning.references`` that ``methods.run`` holds and that do not learn."""
    return [m for m in learning.references if m in settings.methods and not settings.methods[m].learns]


def check_learning(settings: Settings, learning: LearningSettings) -> None:
    """``learning.dataset`` is one the profile prepares; every cap and ``learning.start_order`` name methods of
    ``learning.methods``, the caps keys of their options (:func:`capped_settings` of each learner).

    Raises:
        ConfigError: naming the key, what was expected and what was found.
    """
    if learning.dataset not in settings.run.datasets:
        raise ConfigError(f"config.yaml: key 'learning.dataset' is {learning.dataset!r}, which profile "
                          f"{settings.profile!r} does not run (profiles.{settings.profile}.datasets: "
                          f"{', '.join(settings.run.datasets)})")
    for key, names in (("caps", learning.caps), ("start_order", learning.start_order)):
        unknown = sorted(set(names) - set(learning.methods))
        if unknown:
            raise ConfigError(f"config.yaml: key 'learning.{key}' names {', '.join(map(repr, unknown))}, which "
                              f"'learning.methods' does not list (found {', '.join(learning.methods)})")
    for method in learning_methods(settings, learning):
        capped_settings(settings, learning, method)


def capped_settings(settings: Settings, learning: LearningSettings, method: str) -> Settings:
    """``settings`` with ``method``'s options at its cap: ``learning.caps.<method>`` merged over them (mappings key by
    key) and rebuilt by the method's class, so a bad key or value fails as in its own section.

    Raises:
        ConfigError: the merged options do not build (the message names ``learning.caps.<method>``).
    """
    cap = learning.caps.get(method)
    if not cap:
        return settings
    m = settings.methods[method]
    where = f"learning.caps.{method}"
    try:
        options = m.controller_class.options_from_plain(name=method, data=merge(to_plain(m.options), cap),
                                                        where=where)
    except (ConfigError, TypeError, ValueError, KeyError) as err:
        raise ConfigError(f"config.yaml: key '{where}': {err}") from None
    return dataclasses.replace(settings, methods={**settings.methods, method: dataclasses.replace(m, options=options)})


def learning_train_slice(settings: Settings, learning: LearningSettings, method: str) -> dict:
    """What a ``learning_train`` job reads: :func:`train_slice` of the method at its cap, ``snapshots`` (the ladder,
    and the untrained model) and ``validation_days`` (the days it must not train on)."""
    job = train_slice(capped_settings(settings, learning, method), method)
    job["snapshots"] = {"fractions": list(learning.ladder), "untrained": True}
    job["validation_days"] = learning.validation_days
    return job


def learning_score_slice(settings: Settings, learning: LearningSettings, method: str) -> dict:
    """What a ``learning_score`` job reads: :func:`evaluate_slice` of the method at its cap (a reference method as
    it is) less the day limits, and ``validation_days`` (the days it scores)."""
    job = {k: v for k, v in evaluate_slice(capped_settings(settings, learning, method), method).items()
           if k != "eval_days"}
    job["validation_days"] = learning.validation_days
    return job
