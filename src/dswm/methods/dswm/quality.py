"""World-model quality on evaluated days (paper Fig. 12, Section V-H): how well the DSWM world model imagines the
days its controller actually played.

The controller is replayed on evaluated days through the project's evaluation (``dswm.protocol.replay``: every
observation o_t and executed action a_t recorded in a ``DayPlay``, the realized served ratios SR_t stepped again with
those actions). The same seed, model and days give the main evaluation's trajectory again (the job compares the day
scores). From that record (``play`` below), with the model alone:

* open-loop demand error (:func:`open_loop_maps`, :func:`demand_errors`): from the posterior at slot t (o_0..o_t
  filtered, as the planner does), the prior rolled k = 1..H steps along the EXECUTED actions a_t..a_{t+k-1}; its
  ensemble-mean map against the realized x_{t+k}, for every start t with t + H <= T - 1. Also the planner's
  anchored map rho x_t + (1 - rho) mean and the persistence map x_t, on the same starts.
* imagined return (:func:`imagined_rewards`): what the planner believed of the action it executed: at every slot,
  the first imagined step of the planner's own scorer (``dswm.methods.dswm.planner.imagined_step``: prior step with
  a_t, anchored demand, fleet moved by the environment's rules, the model's service head) gives SR_hat_{t+1}; the
  day's imagined return is their mean over the T - 1 decisions, its realized return the mean of SR_{t+1}.

Maps are in the tensor's normalized demand units (per cell and slot).
"""
from __future__ import annotations

import numpy as np
import torch

from dswm.methods.dswm.planner import ImaginedWorld, StepScoring, imagined_step
from dswm.methods.dswm.rssm import LatentState, map_state, stack_states
from dswm.sim.core import fleet_state_from_obs
from dswm.sim.physics import ServiceParams


@torch.no_grad()
def posteriors(model, play) -> LatentState:
    """The planner's posterior at every decision slot: fields (T-1, .), row t after filtering o_0..o_t (with the
    executed a_0..a_{t-1}), as ``DSWMController`` filters them."""
    device = model.cells.device
    state = model.rssm.initial(1, device=device)
    prev = torch.zeros(1, *play.actions.shape[1:], device=device)
    out = []
    for obs, action in zip(play.obs, play.actions):
        state = model.filter_step(state, prev, torch.as_tensor(obs["demand"], device=device)[None],
                                  torch.as_tensor(obs["fleet"], device=device)[None],
                                  torch.as_tensor(obs["time"], device=device)[None])
        out.append(map_state(state, lambda x: x[0]))
        prev = torch.as_tensor(action, device=device)[None].clamp(-1.0, 1.0)
    return stack_states(out)


@torch.no_grad()
def open_loop_maps(model, posts: LatentState, actions: np.ndarray, starts: np.ndarray, horizon: int) -> np.ndarray:
    """The model's open-loop imagination from the posteriors at ``starts`` along the executed actions.

    Args:
        posts: posteriors, fields (T-1, .) (:func:`posteriors`); actions: (T-1, K, 3) executed a_0..a_{T-2};
        starts: (N,) slots t with t + horizon <= T - 1; horizon: imagined steps H.
    Returns:
        (H, N, G) the ensemble-mean map of imagined step k (row k-1) from start t: the model's x_hat_{t+k}.
    """
    device = model.cells.device
    starts = np.asarray(starts, dtype=np.int64)
    if len(starts) and starts.max() + horizon > len(actions):
        raise ValueError(f"open-loop imagination: start {starts.max()} + horizon {horizon} passes the day's last "
                         f"action ({len(actions)} decisions)")
    act = torch.as_tensor(np.clip(actions, -1.0, 1.0), dtype=torch.float32, device=device).flatten(1)  # (T-1, A)
    idx = torch.as_tensor(starts, device=device)
    state = map_state(posts, lambda x: x[idx])
    maps = []
    for k in range(horizon):
        state = model.rssm.img_step(state, act[idx + k], sample=False)
        maps.append(model.demand_members(model.rssm.feat(state)).mean(0))
    return torch.stack(maps).cpu().numpy()


def aligned_maps(pred: np.ndarray, demand: np.ndarray,
                 starts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The maps an imagined step is judged by, in float64: (x_t (N, G) of each start t, x_{t+k} (H, N, G) of each
    step k = 1..H, the imagined maps ``pred`` (H, N, G)); demand: (T, G) realized maps; starts: (N,) start slots."""
    starts = np.asarray(starts, dtype=np.int64)
    now = demand[starts].astype(np.float64)
    truth = np.stack([demand[starts + k] for k in range(1, pred.shape[0] + 1)]).astype(np.float64)
    return now, truth, pred.astype(np.float64)


def demand_errors(pred: np.ndarray, demand: np.ndarray, starts: np.ndarray, rho: float) -> dict[str, np.ndarray]:
    """Mean squared demand error per imagined step, over starts and cells.

    Args:
        pred: (H, N, G) imagined maps (:func:`open_loop_maps`); demand: (T, G) realized maps x_0..x_{T-1};
        starts: (N,) the start slots of ``pred``'s rows; rho: the planner's anchor coefficient.
    Returns:
        {"mse_model", "mse_anchored", "mse_persistence"}: (H,) each, entry k-1 the mean over starts t and cells of
        the squared error against x_{t+k} of the model's map, of rho x_t + (1 - rho) model map, and of x_t.
    """
    now, truth, model = aligned_maps(pred, demand, starts)
    anchored = rho * now[None] + (1.0 - rho) * model
    return {"mse_model": ((model - truth) ** 2).mean(axis=(1, 2)),
            "mse_anchored": ((anchored - truth) ** 2).mean(axis=(1, 2)),
            "mse_persistence": ((now[None] - truth) ** 2).mean(axis=(1, 2))}


@torch.no_grad()
def imagined_rewards(model, posts: LatentState, play, *, grid, scenario, rho: float,
                     lambda_u: float) -> tuple[np.ndarray, np.ndarray]:
    """What the planner believed of each executed action: the first imagined step of its scorer.

    Returns:
        (SR_hat (T-1,), reward (T-1,)): entry t the imagined SR_{t+1} of a_t from the posterior at t, and the
        planner's reward SR_hat - lambda_u u of that step.
    """
    device = model.cells.device
    fleet = fleet_state_from_obs(np.stack([o["fleet"] for o in play.obs]), grid, scenario)
    fleet = type(fleet)(*(t.to(device) for t in fleet))
    act = torch.as_tensor(play.actions, dtype=torch.float32, device=device).clamp(-1.0, 1.0)    # (T-1, K, 3)
    # x_now of each row: the observed map of its slot (the scorer's (G,) broadcast over the N = T-1 rows).
    x_now = torch.as_tensor(play.demand[: len(play.actions)], device=device).flatten(1)       # (T-1, G)
    world = ImaginedWorld(cells=grid.cells(device=device), geom=grid.geometry(), scenario=scenario,
                          params=ServiceParams.from_scenario(scenario))
    kw = dict(x_now=x_now, x_true=None, world=world, first=True)
    sr_hat = imagined_step(model, fleet, posts, act, None, None, **kw,
                           scoring=StepScoring(rho=rho, lambda_u=0.0, continuation="hold"))[-1]
    reward = imagined_step(model, fleet, posts, act, None, None, **kw,
                           scoring=StepScoring(rho=rho, lambda_u=lambda_u, continuation="hold"))[-1]
    return sr_hat.cpu().numpy().astype(np.float64), reward.cpu().numpy().astype(np.float64)


def day_quality(model, play, *, grid, scenario, horizon: int, rho: float, lambda_u: float) -> dict:
    """Everything the figure needs of one played day.

    Returns:
        {"starts": (N,) start slots 0..T-1-H, **demand_errors (H,) each, "sr_hat", "reward", "sr" (T-1,) the
        imagined and realized SR_1..SR_{T-1}, "one_step": (T, R, C) the model's one-step map of every slot
        (x_hat_t from the posterior at t-1 and a_{t-1}; NaN at slot 0)}.
    Raises:
        ValueError: the day has fewer than ``horizon`` decisions.
    """
    n_dec = len(play.actions)
    if not 0 < horizon <= n_dec:
        raise ValueError(f"figures.wm_quality.horizon: expected 1..{n_dec} (the decisions of a day), found {horizon}")
    posts = posteriors(model, play)
    demand = play.demand.reshape(play.demand.shape[0], -1)
    starts = np.arange(0, n_dec - horizon + 1)
    errors = demand_errors(open_loop_maps(model, posts, play.actions, starts, horizon), demand, starts, rho)
    one = open_loop_maps(model, posts, play.actions, np.arange(n_dec), 1)[0]                 # (T-1, G)
    one_step = np.concatenate([np.full((1, one.shape[1]), np.nan, dtype=np.float32), one.astype(np.float32)])
    sr_hat, reward = imagined_rewards(model, posts, play, grid=grid, scenario=scenario, rho=rho, lambda_u=lambda_u)
    return {"starts": starts, **errors, "sr_hat": sr_hat, "reward": reward, "sr": play.sr[1:],
            "one_step": one_step.reshape(play.demand.shape)}


# ---- anchoring per imagined step (the room-fill candidate, dswm.pipeline.room_fill) ----------------------------
def anchor_moments(pred: np.ndarray, demand: np.ndarray, starts: np.ndarray) -> dict[str, np.ndarray]:
    """The sums over starts and cells that the least-squares anchoring of each imagined step needs.

    With x = x_t, m = the model's map of step k and y = x_{t+k}, the anchored map rho x + (1 - rho) m has squared
    error sum (m - y + rho (x - m))^2 = ``mm`` + 2 rho ``xm_my`` + rho^2 ``xm``. Sums add over days.

    Args:
        pred: (H, N, G) imagined maps (:func:`open_loop_maps`); demand: (T, G) realized maps; starts: (N,) start slots.
    Returns:
        {"xm": sum (x - m)^2, "xm_my": sum (x - m)(m - y), "mm": sum (m - y)^2, "n": number of terms}, (H,) each.
    """
    now, truth, model = aligned_maps(pred, demand, starts)
    d, e = now[None] - model, model - truth
    n = np.full(pred.shape[0], float(d.shape[1] * d.shape[2]))
    return {"xm": (d * d).sum(axis=(1, 2)), "xm_my": (d * e).sum(axis=(1, 2)), "mm": (e * e).sum(axis=(1, 2)), "n": n}


def add_moments(a: dict[str, np.ndarray] | None, b: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The moments of two sets of days together (``a`` None: ``b``)."""
    return dict(b) if a is None else {k: a[k] + b[k] for k in b}


def fit_rho_steps(moments: dict[str, np.ndarray]) -> np.ndarray:
    """rho_k minimizing the squared error of rho_k x_t + (1 - rho_k) m_k against x_{t+k}, per step k, clipped to
    [0, 1]: rho_k = -``xm_my`` / ``xm`` (the least-squares solution); 1 (persistence) where x_t = m_k everywhere.

    Returns:
        (H,) rho_1..rho_H.
    """
    xm, xm_my = np.asarray(moments["xm"], dtype=np.float64), np.asarray(moments["xm_my"], dtype=np.float64)
    rho = np.divide(-xm_my, xm, out=np.ones_like(xm), where=xm > 0)
    return np.clip(rho, 0.0, 1.0)


def anchored_mse(moments: dict[str, np.ndarray], rho) -> np.ndarray:
    """(H,) mean squared error per step of the map anchored by ``rho`` (a number, or one per step)."""
    rho = np.broadcast_to(np.asarray(rho, dtype=np.float64), moments["xm"].shape)
    return (moments["mm"] + 2.0 * rho * moments["xm_my"] + rho * rho * moments["xm"]) / moments["n"]
