"""HRL-TPRA (Yuan et al. 2025, re-implemented; docs/PROTOCOL.md §5): hierarchical RL with pointer-network trajectory
planning and per-UAV resource actors.

* High level (:mod:`.pointer`): every ``macro_slots`` slots, a pointer network over the top-N demand cells of the
  current observed map assigns each UAV a distinct target cell (GRU decoder stepping through the UAVs, attention
  with the chosen cells masked). Trained by a clipped policy gradient with a learned baseline on the macro-slot's
  summed reward plus a discounted bootstrap (:mod:`.learner`).
* Low level (:mod:`.actors`): one resource actor and one critic PER UAV (separate weights), stacked as (K, in, out)
  parameters and evaluated with one batched matrix product per layer instead of K modules in a loop (the source's
  bottleneck: benchmarks/bench_hrl_tpra.py). Each sees its own state, its target and its local demand, and outputs
  a fine move around the move toward the target and its bandwidth logit (:mod:`.features`). PPO with GAE; a day's
  end truncates, so both levels bootstrap there.
* Training (:mod:`.training`) steps ``n_envs`` training days per round in one core call per slot.
"""
from dswm.methods.hrl_tpra.controller import HRLTPRAController
from dswm.methods.hrl_tpra.settings import HRLTPRASettings

__all__ = ["HRLTPRAController", "HRLTPRASettings"]
