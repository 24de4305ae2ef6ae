"""TD-MPC diagnostics: does the learned reward rank candidate actions at one state as the environment does?

MPPI picks, per slot, the sampled action sequences with the highest model return; its choice is only as good as
the model's ORDER of the candidates at that state, not its mean error over the data. :func:`one_step_rewards`
gives the environment's own reward of N candidate actions from one episode's current state (paper eq. 7, the
computation of ``FleetCore.step`` without advancing the core), :func:`reward_ranking` compares it with the model's
predicted reward R(z, a) of the same candidates: the rank correlation, and the true reward of the candidate the
model ranks first against the candidates' mean and best. ``benchmarks/diagnose_tdmpc.py`` runs both on a learning
run's models (README, "Learning curves").
"""
from __future__ import annotations

from typing import Any, Mapping, NamedTuple

import numpy as np
import torch

from dswm.sim.fleet import FleetState, available, fleet_step
from dswm.sim.physics import service


@torch.no_grad()
def one_step_rewards(core, episode: int, actions: torch.Tensor) -> torch.Tensor:
    """The reward ``core.step`` would return for each of N candidate actions of one episode; the core is unchanged.

    Args:
        core: a ``FleetCore`` after ``reset``/``step`` (slot t < T); episode: index into its current batch;
        actions: (N, K, 3) candidates (clipped to [-1, 1] as the environment clips them).
    Returns:
        (N,) rewards SR - beta (1 - SR) - alpha E / (E_hover K) of the slot t -> t + 1.
    """
    if core.t >= core.scenario.slots_per_day - 1:
        raise RuntimeError("one_step_rewards: the day is over, no step is left")
    a = actions.clamp(-1.0, 1.0).to(core.demand.dtype)
    n = a.shape[0]
    state = FleetState(*(x[episode] for x in core.state)).expand(n)
    nxt, energy = fleet_step(state, a, core.geom, core.scenario)
    x = core.demand[core.days[episode], core.t + 1].unsqueeze(0).expand(n, -1)
    res = service(x, nxt.pos, available(nxt), core.cells, params=core.params, bw_logit=a[..., 2])
    s = core.scenario
    return res.sr - s.reward_beta * (1.0 - res.sr) - s.reward_alpha * energy.sum(-1) / (core.hover_energy_j * s.n_uavs)


def rank_correlation(a, b) -> float:
    """Spearman's rank correlation of two 1-D samples (ranks by argsort; continuous values have no ties)."""
    ra = np.argsort(np.argsort(np.asarray(a, dtype=np.float64)))
    rb = np.argsort(np.argsort(np.asarray(b, dtype=np.float64)))
    if ra.size < 2:
        return float("nan")
    return float(np.corrcoef(ra, rb)[0, 1])


class Ranking(NamedTuple):
    """How the model orders N candidate actions at one state."""

    spearman: float
    """Rank correlation of the predicted and the true one-step rewards."""
    chosen: float
    """True reward of the candidate with the highest predicted reward."""
    mean: float
    """Mean true reward of the candidates."""
    best: float
    """Highest true reward of the candidates."""


@torch.no_grad()
def reward_ranking(model, core, obs: Mapping[str, Any], episode: int, actions: torch.Tensor) -> Ranking:
    """The model's predicted reward R(h(o), a) of each candidate against :func:`one_step_rewards`.

    Args:
        model: a ``TOLD``; core: the ``FleetCore`` whose current observation is ``obs`` (batched);
        episode: index into the batch; actions: (N, K, 3) candidates.
    """
    tensors = [torch.as_tensor(np.asarray(obs[k])[episode:episode + 1], dtype=torch.float32)
               for k in ("demand", "fleet", "time")]
    z = model.encode(*tensors)
    n = actions.shape[0]
    _, predicted = model.next(z.expand(n, -1), actions.reshape(n, -1).to(z.dtype))
    true = one_step_rewards(core, episode, actions)
    i = int(predicted.argmax())
    return Ranking(spearman=rank_correlation(predicted.numpy(), true.numpy()), chosen=float(true[i]),
                   mean=float(true.mean()), best=float(true.max()))
