"""Prediction-guided task selection (PGMORL, Xu et al. 2020, Section 4.2), as EMORL-TCTO runs it.

A task is (parent policy, weight): continue training the parent with PPO on the scalarized reward w . objectives.
Which tasks a generation trains is decided by predicting, for every archive member p and every candidate weight w,
the objective vector the task would reach, F_p + dF_p(w), and choosing greedily the tasks whose predicted points
raise the archive's hypervolume most.

* Improvement model of a policy p (:func:`fit_improvement`): per objective j, dF_j(w) = c_j + s_j w_j, fitted by
  weighted least squares, with a ridge penalty on the slope s_j, to the (weight, objective change) pairs of ALL
  tasks done so far, each weighted by exp(-d^2 / (2 b^2)), d the distance of the task's parent to p in objective
  space (each objective divided by its range over every policy measured so far; :func:`neighbour_weights`), b the
  bandwidth. As in PGMORL the data come from the policy's neighbourhood, so a policy whose own lineage has tried
  one weight still gets a slope from its neighbours' other weights. PGMORL fits a hyperbolic (tanh) curve per
  objective with four parameters; with the few tasks of a small budget that fit is underdetermined, and the linear
  form is its first-order version: the improvement along objective j grows with the weight put on j.
* Greedy choice (:func:`select_tasks`): n times, the untaken candidate that maximizes the hypervolume of (archive
  points + predicted points already chosen + its own predicted point); ties (when no predicted point enlarges the
  front, e.g. when every task is predicted to lose ground) go to the larger hypervolume of the predicted point
  alone (the volume it dominates: a scale-free measure of how good it is), then to the earlier candidate (archive
  order, then lattice order). PGMORL adds a sparsity term to the hypervolume; it is left out here (the
  hypervolume is the stated metric).
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from dswm.methods.emorl_tcto.archive import N_OBJ, hypervolume


class ImprovementModel(NamedTuple):
    """dF_j(w) = intercept_j + slope_j * w_j for each objective j."""

    intercept: np.ndarray  # (3,)
    slope: np.ndarray  # (3,)

    def predict(self, weights) -> np.ndarray:
        """(W, 3) predicted objective changes of training with each of the weights (W, 3)."""
        w = np.asarray(weights, dtype=np.float64).reshape(-1, N_OBJ)
        return self.intercept[None, :] + self.slope[None, :] * w


def fit_improvement(weights, deltas, ridge: float, sample_weight=None) -> ImprovementModel:
    """Fit the improvement model to (weight, objective change) pairs.

    Per objective j, minimizes sum_i k_i (d_ij - c_j - s_j w_ij)^2 + ridge * s_j^2 (intercept unpenalized; the
    k_i scaled to sum 1, so ridge compares with a weighted variance of the weights): with k-weighted means,
    s_j = sum k (w - mean w)(d - mean d) / (sum k (w - mean w)^2 + ridge), c_j = mean d - s_j mean w.
    With one pair, or one weight value, the slope is 0 and the prediction is the (weighted) mean change.

    Args:
        weights: (N, 3) the tasks' weights; deltas: (N, 3) their objective changes (child minus parent); N >= 0.
        ridge: the slope's penalty (>= 0).
        sample_weight: (N,) k_i >= 0, or None for equal weights.

    Returns:
        The model; with N = 0 (or all k_i = 0) it predicts no change.
    """
    w = np.asarray(weights, dtype=np.float64).reshape(-1, N_OBJ)
    d = np.asarray(deltas, dtype=np.float64).reshape(-1, N_OBJ)
    k = np.ones(len(w)) if sample_weight is None else np.asarray(sample_weight, dtype=np.float64).reshape(-1)
    if len(w) != len(d) or len(k) != len(w):
        raise ValueError(f"fit_improvement: {len(w)} weights, {len(d)} objective changes, {len(k)} sample weights")
    if len(w) == 0 or not k.sum() > 0:
        return ImprovementModel(np.zeros(N_OBJ), np.zeros(N_OBJ))
    k = k / k.sum()
    w_mean, d_mean = k @ w, k @ d
    wc, dc = w - w_mean, d - d_mean
    denom = k @ (wc * wc) + ridge
    slope = np.where(denom > 0, (k @ (wc * dc)) / np.where(denom > 0, denom, 1.0), 0.0)
    return ImprovementModel(d_mean - slope * w_mean, slope)


def neighbour_weights(parents, member, scale, bandwidth: float) -> np.ndarray:
    """(N,) exp(-|(parent_i - member) / scale|^2 / (2 bandwidth^2)): how much task i (launched from a parent with
    objective vector parents[i]) tells about training the policy with objective vector ``member``.

    Args:
        parents: (N, 3) objective vectors of the tasks' parents; member: (3,); scale: (3,) per-objective ranges
            (a zero range counts as 1: the objective does not separate policies).
    """
    scale = np.where(np.asarray(scale, dtype=np.float64) > 0, scale, 1.0)
    z = (np.asarray(parents, dtype=np.float64).reshape(-1, N_OBJ) - np.asarray(member, dtype=np.float64)) / scale
    return np.exp(-(z * z).sum(axis=1) / (2.0 * bandwidth ** 2))


class Task(NamedTuple):
    """A chosen task: the archive row of its parent, the lattice index of its weight, and the prediction."""

    parent: int
    weight: int
    predicted: np.ndarray  # (3,) predicted objective vector of the child


def select_tasks(archive, predicted, weights, n_tasks: int, ref) -> list[Task]:
    """Greedy prediction-guided choice of ``n_tasks`` tasks.

    Args:
        archive: (A, 3) objective vectors of the archive members (the parents), A >= 1.
        predicted: (A, W, 3) predicted objective vector of member a trained with weight w.
        weights: (W, 3) the candidate weights.
        n_tasks: tasks to choose (at most A x W).
        ref: (3,) the hypervolume's reference point.

    Returns:
        The tasks in the order chosen.
    """
    f = np.asarray(archive, dtype=np.float64).reshape(-1, N_OBJ)
    pred = np.asarray(predicted, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64).reshape(-1, N_OBJ)
    a, n_w = len(f), len(w)
    if a < 1 or pred.shape != (a, n_w, N_OBJ):
        raise ValueError(f"select_tasks: expected predictions of shape ({a}, {n_w}, {N_OBJ}) for {a} archive "
                         f"members and {n_w} weights, found {pred.shape}")
    if not 1 <= n_tasks <= a * n_w:
        raise ValueError(f"select_tasks: expected 1 <= n_tasks <= {a * n_w}, found {n_tasks}")
    # the volume each predicted point dominates alone (the tie-break)
    alone = np.array([[hypervolume(pred[i, k][None, :], ref) for k in range(n_w)] for i in range(a)])
    points: list[np.ndarray] = list(f)
    taken: set[tuple[int, int]] = set()
    chosen: list[Task] = []
    for _ in range(n_tasks):
        best, best_key = None, None
        for i in range(a):
            for k in range(n_w):
                if (i, k) in taken:
                    continue
                key = (hypervolume(np.vstack(points + [pred[i, k]]), ref), alone[i, k])
                if best_key is None or key > best_key:
                    best, best_key = (i, k), key
        taken.add(best)
        points.append(pred[best])
        chosen.append(Task(best[0], best[1], pred[best].copy()))
    return chosen
