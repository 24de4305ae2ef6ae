"""TD-MPC (Hansen, Wang, Su 2022, "Temporal Difference Learning for Model Predictive Control"), for the UAV fleet:
a task-oriented latent dynamics model (TOLD) learned by latent consistency, reward and TD value losses, and MPPI
in its latent space at decision time, closed by the learned value. docs/PROTOCOL.md §5.

* :mod:`.settings`: the typed settings (config.yaml ``methods.tdmpc``, its pre-collection included).
* :mod:`.model`: TOLD (encoder, latent dynamics, reward, twin Q, policy).
* :mod:`.replay`: the shared episode replay with rewards, sampled as (H+1)-observation windows.
* :mod:`.learner`: the losses, one gradient step, the target network.
* :mod:`.planner`: MPPI.
* :mod:`.agent`: training (pre-collection, own interaction, checkpoints) and the controller.
* :mod:`.diagnose`: how the learned reward ranks candidate actions against the environment's own rewards.
"""
from dswm.methods.tdmpc.agent import TDMPCController
from dswm.methods.tdmpc.settings import TDMPCSettings

__all__ = ["TDMPCController", "TDMPCSettings"]
