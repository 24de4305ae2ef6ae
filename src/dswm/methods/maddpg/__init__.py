"""MADDPG (Lowe et al. 2017, "Multi-agent actor-critic for mixed cooperative-competitive environments") for the
UAV fleet: centralized training, decentralized execution, deterministic continuous actions (docs/PROTOCOL.md §5).

* Actor: ONE actor shared by the K UAVs, fed each UAV's local observation (a crop of the w+1 log1p demand maps
  around its own cell with the other UAVs' occupancy, its own fleet features, the time phase) and a learned
  embedding of its index. Sharing keeps the parameter count independent of K, lets every UAV learn from every
  UAV's experience (the UAVs are interchangeable but for their position and battery), and lets evaluation act
  on B days x K UAVs in one pass; the index embedding and the local input keep the agents' features apart
  (their cross-agent spread is logged, ``diag/agent_feature_std``). Built from ``torchrl.modules.MultiAgentMLP``
  (shared parameters, decentralized).
* Critic: one centralized Q(x, a_1..a_K) on the joint observation (the environment's whole observation, the
  union of the agents') and the joint action. The reward is the fleet's team reward, so the paper's K critics
  would share one target; they are one network. It is a plain torch module rather than a centralized
  ``MultiAgentMLP``, which would take K per-agent inputs and concatenate them: the common maps would have to be
  copied into every agent's input (K-fold wider first layer), and the actor objective (agent i's action replaced,
  the others' from the replay) would need K full critic passes, where splitting the first layer makes it one.
* Training (:mod:`.training`) runs through ``dswm.sim.env.UAVFleetParallelEnv`` (the PettingZoo parallel API)
  built on the TRAINING core; the gradient step is in :mod:`.learner`, the buffer in :mod:`.replay`.
"""
from dswm.methods.maddpg.controller import MADDPGController
from dswm.methods.maddpg.settings import MADDPGSettings

__all__ = ["MADDPGController", "MADDPGSettings"]
