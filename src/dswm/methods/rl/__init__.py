"""Model-free reinforcement learning: the plumbing every learner of this class shares, and the SB3 methods.

* :mod:`dswm.methods.rl.spaces`: the one flat observation (``flat_observation``, ``observation_dim``,
  ``observation_space``; demand through ``log1p``) and the flat action (``flat_action``, ``fleet_action``),
  ``FlatFleetEnv`` (the Gymnasium view with both);
* :mod:`dswm.methods.rl.vec_env`: ``FleetVecEnv``, SB3's ``VecEnv`` stepping n_envs training days in one
  ``FleetCore`` call, recording the days of every episode;
* :mod:`dswm.methods.rl.logger`: ``HistoryWriter``, SB3's scalars as a training manifest's history;
* :mod:`dswm.methods.rl.common`: what the SB3 learners share: ``SB3Params`` and ``PPOParams`` (the PPO
  hyper-parameters of ``ppo`` and of EMORL-TCTO's inner learner), ``DumpEachUpdate``, ``rng_states``;
* :mod:`dswm.methods.rl.sb3`: ``PPOController`` (``ppo``) and ``SACController`` (``sac``) with their settings, the
  one method module of this package (the others are shared infrastructure: a method may import them, no
  method imports ``sb3``).

Submodules are imported where used (SB3 is imported by the last four only).
"""
