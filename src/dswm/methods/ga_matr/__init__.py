"""GA-MATR (Feng et al. 2024, "graph-attention multi-agent trust-region" RL with a fairness regularizer),
re-implemented for the UAV fleet (docs/PROTOCOL.md §5).

* Each UAV is a node. Its token is built from its own fleet features, a crop of the w+1 log1p demand maps around
  its cell and the time phase, plus a learned embedding of its index (:mod:`.networks`). Graph-attention blocks
  run masked multi-head self-attention among the UAV tokens (an unavailable UAV, returning or charging, receives
  no attention), cross-attention from each UAV to P x P pooled demand-context tokens, and a feed-forward layer.
* Policy: ONE network shared by the K UAVs, with a Gaussian per UAV over (dx, dy, bw_logit) (mean in (-1, 1),
  a learned std per agent and component), actions clipped to [-1, 1]. Shared parameters keep the size
  independent of K, let every UAV learn from every UAV's experience, and act on B days x K UAVs in one pass;
  the index embedding and the local crop keep the agents apart (their cross-agent embedding std is logged,
  ``diag/agent_embedding_std``: the paper's first version collapsed to identical embeddings).
* Training (:mod:`.happo`, :mod:`.training`): HAPPO's sequential trust-region update, agents one by one in a
  random permutation per update, each agent's clipped surrogate weighted by the product of the ratios of the
  agents updated before it and taken through its own log-probabilities; a centralized critic V(s) on the flat
  global observation; GAE that bootstraps at the day's end (a truncation). The learner's reward is eq. 7 minus
  ``fairness_weight`` times the std / mean of the UAVs' served load (``FleetCore.uav_load``); evaluation scores
  eq. 7 alone.
"""
from dswm.methods.ga_matr.controller import GAMATRController
from dswm.methods.ga_matr.settings import GAMATRSettings

__all__ = ["GAMATRController", "GAMATRSettings"]
