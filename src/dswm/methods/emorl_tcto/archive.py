"""The Pareto archive and the weight space of EMORL-TCTO: non-dominated filtering, hypervolume, the lattice of
weights, the evenly spread warm-up weights and the rule that picks the executed member.

Objective vectors are maximized, in the order of :data:`OBJECTIVES`: the day's mean served ratio, minus the
day's mean fleet energy per slot over the fleet's hover energy (``FleetCore.hover_energy_j * K``, the
normalization of the core's reward), and the day's mean Jain index.
"""
from __future__ import annotations

import numpy as np
from pymoo.indicators.hv import HV
from pymoo.util.nds.non_dominated_sorting import NonDominatedSorting
from pymoo.util.ref_dirs import get_reference_directions

OBJECTIVES = ("served_ratio", "neg_energy", "jain")
"""The maximized objectives, in the order of every objective vector and weight."""
N_OBJ = len(OBJECTIVES)


def _as_matrix(points, where: str) -> np.ndarray:
    f = np.asarray(points, dtype=np.float64)
    if f.ndim != 2 or f.shape[1] != N_OBJ:
        raise ValueError(f"{where}: expected objective vectors of shape (N, {N_OBJ}), found {f.shape}")
    if not np.isfinite(f).all():
        raise ValueError(f"{where}: non-finite objective value in row {int(np.argwhere(~np.isfinite(f))[0, 0])}")
    return f


def non_dominated(points) -> list[int]:
    """Indices (ascending) of the points no other point dominates, each objective maximized.

    A point dominates another when it is at least as good in every objective and better in one (pymoo's
    non-dominated sorting on the negated vectors). Identical vectors do not dominate each other; of a group of
    identical non-dominated vectors only the FIRST is kept (a copy adds nothing to the front and the older member
    has the longer record).

    Args:
        points: (N, 3) objective vectors; N may be 0.
    """
    f = _as_matrix(points, "non_dominated")
    if len(f) == 0:
        return []
    front = sorted(int(i) for i in NonDominatedSorting().do(-f, only_non_dominated_front=True))
    kept: list[int] = []
    for i in front:
        if not any(np.array_equal(f[i], f[j]) for j in kept):
            kept.append(i)
    return kept


def hypervolume(points, ref) -> float:
    """Volume of the objective space the points dominate above the reference point ``ref`` (maximization;
    pymoo's exact indicator on the negated vectors). Points that do not dominate ``ref`` add nothing."""
    f = _as_matrix(points, "hypervolume")
    ref = np.asarray(ref, dtype=np.float64)
    if len(f) == 0:
        return 0.0
    return float(HV(ref_point=-ref)(-f))


def reference_point(max_energy_ratio: float) -> np.ndarray:
    """The hypervolume's reference point: every reachable objective vector dominates it.

    Served ratio and Jain index are >= 0; a UAV's slot energy over the hover energy is at most
    ``max_energy_ratio`` (max over the speeds it can fly of P(V) / P(0)), so -energy >= -max_energy_ratio.
    """
    return np.array([0.0, -float(max_energy_ratio), 0.0])


def weight_lattice(divisions: int) -> np.ndarray:
    """(W, 3) the Das-Dennis lattice on the simplex (every weight k / divisions, summing to 1), pymoo's order."""
    w = get_reference_directions("das-dennis", N_OBJ, n_partitions=divisions)
    return np.round(w * divisions) / divisions


def warmup_weights(n: int, divisions: int) -> np.ndarray:
    """(n, 3) evenly spread warm-up weights: farthest-point sampling of :func:`weight_lattice` from the served-ratio
    corner (1, 0, 0), the paper's primary metric; ties go to the earlier lattice weight.

    Farthest-point sampling is written here because pymoo's Riesz-energy directions need n >= 3 and come out of
    an optimization (not exactly on the lattice); this is exact, deterministic and stays on the candidate lattice.
    """
    lattice = weight_lattice(divisions)
    if not 1 <= n <= len(lattice):
        raise ValueError(f"warmup_weights: expected 1 <= n <= {len(lattice)}, found {n}")
    chosen = [int(np.flatnonzero(np.all(lattice == np.array([1.0, 0.0, 0.0]), axis=1))[0])]
    dist = np.linalg.norm(lattice - lattice[chosen[0]], axis=1)
    while len(chosen) < n:
        nxt = int(np.argmax(dist))  # the first of the farthest
        chosen.append(nxt)
        dist = np.minimum(dist, np.linalg.norm(lattice - lattice[nxt], axis=1))
    return lattice[chosen]


def select_member(objectives, rule: str, weight=None) -> int:
    """Row of the executed member among archive objective vectors ``objectives`` (N, 3), in archive order.

    ``best_served_ratio``: the highest served ratio; ``max_scalarized``: the highest ``weight . objectives``.
    Ties go to the first row (the oldest member).
    """
    f = _as_matrix(objectives, "select_member")
    if len(f) == 0:
        raise ValueError("select_member: the archive is empty")
    if rule == "best_served_ratio":
        score = f[:, 0]
    elif rule == "max_scalarized":
        score = f @ np.asarray(weight, dtype=np.float64)
    else:
        raise ValueError(f"select_member: unknown rule {rule!r}; expected best_served_ratio or max_scalarized")
    return int(np.argmax(score))
