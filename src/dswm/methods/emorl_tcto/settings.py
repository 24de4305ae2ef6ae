"""EMORL-TCTO's settings (config.yaml ``methods.emorl_tcto``, one profile's budget merged in): its own and its inner
PPO learner's (the shared :class:`dswm.methods.rl.common.PPOParams`, read from this same section)."""
from __future__ import annotations

import dataclasses
from typing import ClassVar, Literal

from dswm.config import ENUM, setting
from dswm.methods.rl.common import PPOParams

RESUME_FREE = ("generations", "checkpoint_every")
"""Settings a checkpoint may differ in and still resume (more generations continue a shorter run)."""
DECISION_TIME = ("select_rule", "select_weight")
"""Settings read after training only: they pick the executed member of the trained archive, so a change retrains
nothing (``EMORLTCTOController.training_settings`` leaves them out)."""


@dataclasses.dataclass(frozen=True, kw_only=True)
class EMORLTCTOSettings(PPOParams):
    """Population, evolution, prediction, selection and the inner PPO learner (:class:`PPOParams`) of EMORL-TCTO."""

    section: ClassVar[str] = "methods.emorl_tcto"

    # ---- evolution ------------------------------------------------------------------------------------
    n_population: int = setting("count")
    """Warm-up policies (one per evenly spread weight) and tasks trained per generation."""
    warmup_rounds: int = setting("count")
    """PPO rounds (n_envs day-episodes each) of every warm-up task."""
    generations: int = setting("natural")
    """Generations after the warm-up (each trains n_population tasks chosen by prediction)."""
    task_rounds: int = setting("count")
    """PPO rounds of every task of a generation."""
    weight_divisions: int = setting("count")
    """Divisions of the Das-Dennis lattice of weights on the 3-objective simplex: the candidate weights (and the
    pool the warm-up weights are spread over), (d + 1)(d + 2) / 2 of them."""
    prediction_bandwidth: float = setting("positive")
    """Bandwidth of the Gaussian weights of past tasks in a policy's improvement model, in objective space scaled
    per objective by the range over every policy measured (``prediction.neighbour_weights``)."""
    prediction_ridge: float = setting("nonnegative")
    """Ridge penalty on the slope of the improvement model (0: plain least squares)."""
    eval_days: int = setting("count")
    """Training days of the fixed set every policy's objective vector is measured on (all days if fewer)."""
    # ---- executed policy (decision time) ---------------------------------------------------------------
    select_rule: Literal["best_served_ratio", "max_scalarized"] | None = setting(ENUM)
    """The archive member executed: ``best_served_ratio`` (highest mean served ratio on the evaluation days)
    or ``max_scalarized`` (highest select_weight . objectives); None only in a training-settings slice."""
    select_weight: tuple[float, float, float] | None = setting(
        schema={"type": "array", "minItems": 3, "maxItems": 3, "items": {"type": "number", "minimum": 0},
                "description": "[served ratio, -energy, Jain] weights, three numbers >= 0 with a positive sum"})
    """Weights of (served ratio, -energy, Jain) for ``max_scalarized`` (unused by ``best_served_ratio``)."""
    # ---- checkpoints (the inner PPO learner's settings are PPOParams': a round is n_envs day-episodes) ------
    checkpoint_every: int = setting("count")
    """Tasks between checkpoints (one is also written at the end)."""

    def __post_init__(self):
        super().__post_init__()
        n_weights = (self.weight_divisions + 1) * (self.weight_divisions + 2) // 2
        if self.n_population > n_weights:
            self._fail("n_population", f"at most the {n_weights} lattice weights of weight_divisions = "
                                       f"{self.weight_divisions} (one distinct warm-up weight per policy)")
        if (self.select_rule is None) != (self.select_weight is None):
            self._fail("select_weight", "a list of 3 weights exactly when select_rule is set")
        if self.select_weight is not None and sum(self.select_weight) <= 0:
            self._fail("select_weight", "3 numbers >= 0 with a positive sum (served ratio, -energy, Jain)")

    def training(self) -> "EMORLTCTOSettings":
        """These settings without the decision-time ones (:data:`DECISION_TIME` set to None)."""
        return dataclasses.replace(self, select_rule=None, select_weight=None)
