"""EMORL-TCTO (Song et al. 2022, evolutionary multi-objective RL), re-implemented in the style of PGMORL (Xu et al.
2020, prediction-guided multi-objective RL) for the UAV fleet (docs/PROTOCOL.md §5).

* Objectives (:mod:`.objectives`), all maximized: per step served ratio, minus the fleet's slot energy over its
  hover energy, Jain index; a policy's objective vector is their mean over a day, measured deterministically on
  a fixed set of training days. The PPO learner sees the weighted sum w . objectives of its task.
* Archive (:mod:`.archive`): the non-dominated members (pymoo's sorting), hypervolume (pymoo), the weight lattice,
  the warm-up weights, and the rule that picks the executed member (``select_rule``).
* Prediction (:mod:`.prediction`): per-policy improvement models fitted on the (weight, objective change)
  pairs of past tasks, weighted by how near their parents lie to the policy, and the greedy
  hypervolume-maximizing choice of a generation's (policy, weight) tasks.
* Evolution (:mod:`.training`): warm-up, generations, archive updates and checkpoints around one SB3 PPO learner
  whose policy and optimizer state are swapped per task.
"""
from dswm.methods.emorl_tcto.controller import EMORLTCTOController
from dswm.methods.emorl_tcto.settings import EMORLTCTOSettings

__all__ = ["EMORLTCTOController", "EMORLTCTOSettings"]
