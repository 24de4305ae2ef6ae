"""JTORATC's objective on this service model, its association and bandwidth blocks, and the concave surrogate
of the rate that its trajectory block maximizes.

Sun et al. minimize a weighted sum of task delay, UAV energy and (minus) offloaded tasks. On one slot of this
project's service model (docs/PROTOCOL.md §2), for the observed map x (cells with x_g > DEMAND_EPS, total X,
requested rate q_g = x_g u r0) and the fleet after the slot:

* delay D = sum_g (x_g / X) q_g / R_g. A user of cell g sends one slot of r0 traffic over its 1 / (x_g u) part of
  the cell's rate R_g, which takes q_g / R_g slots; D is the mean over users, 1 when every cell gets exactly
  its requested rate. Unlike the served ratio it keeps rewarding rate above the request and punishes a
  starved cell without bound.
* energy E = sum_k P(V_k) / (K P_hover) over the UAVs that move this slot (rotary-wing power, dswm.sim.energy).
* load imbalance L = n sum_k (l_k - 1/n)^2, the squared coefficient of variation of the demand shares l_k of the
  n available UAVs. The source's third term counts offloaded tasks; every cell is served here, so what is left
  of it is how evenly the UAVs carry the demand.

J = w_d D + w_e E + w_l L, with R_g the Shannon rate (paper eq. 3) at the cell's bandwidth share B_g and the
distance to its UAV, computed with the physics' own path loss in float64.
"""
from __future__ import annotations

import dataclasses
import functools
import math
from typing import NamedTuple

import numpy as np
import torch

from dswm.sim.energy import hover_power, rotor_power
from dswm.sim.physics import SHARE_FLOOR_HZ, ServiceParams, associate, path_loss_db
from dswm.sim.scenario import Rotor

LN2 = math.log(2.0)
Z_MIN_M2 = 1.0
"""ln S has a cusp at zero horizontal distance (its slope tends to -inf), so below this squared distance (m^2) the
surrogate is the tangent at Z_MIN_M2: still a lower bound, loose by a few 1e-6 in ln S."""


# ----------------------------------------------------------------------------------------------- channel
def log_snr_hz(z, params: ServiceParams, *, slope: bool = False):
    """ln S with S = P g / N0, a link's SNR times its bandwidth (Hz), at squared horizontal distance z (m^2).

    The physics' path loss (``dswm.sim.physics.path_loss_db``) in float64. With ``slope``, also dln S/dz.
    """
    zt = torch.as_tensor(np.asarray(z, dtype=np.float64)).clamp_min(0.0)
    if slope:
        zt.requires_grad_(True)
    with torch.set_grad_enabled(slope):
        loss_db = path_loss_db(torch.sqrt(zt + params.altitude_m**2), params, horizontal_sq=zt)
        v = math.log(params.tx_power_w / params.noise_psd_w_per_hz) - loss_db * (math.log(10.0) / 10.0)
        if not slope:
            return v.numpy()
        (dv,) = torch.autograd.grad(v.sum(), zt)
    return v.detach().numpy(), dv.numpy()


def shannon_rate(share_hz, v):
    """Rate (bit/s) B log2(1 + S / B) at bandwidth B (floored at SHARE_FLOOR_HZ, as the physics does), v = ln S."""
    b = np.maximum(share_hz, SHARE_FLOOR_HZ)
    return b * np.log1p(np.exp(v) / b) / LN2


class Bridge(NamedTuple):
    """An interval of squared distance on which ln S is not convex, and the line under it."""

    za: float
    zb: float
    va: float
    """The line's value at za (at or below ln S there)."""
    slope: float


def _lower_hull(x: list[float], y: list[float]) -> list[int]:
    """Indices of the lower convex hull of points sorted by x (monotone chain)."""
    hull: list[int] = []
    for i in range(len(x)):
        while len(hull) >= 2 and ((y[hull[-1]] - y[hull[-2]]) * (x[i] - x[hull[-2]])
                                  >= (y[i] - y[hull[-2]]) * (x[hull[-1]] - x[hull[-2]])):
            hull.pop()
        hull.append(i)
    return hull


def _slope_point(s: float, lo: float, hi: float, params: ServiceParams) -> float | None:
    """The z in [lo, hi] where dln S/dz = s (bisection; the slope rises with z on a convex stretch), or None."""
    f = lambda z: float(log_snr_hz(z, params, slope=True)[1]) - s  # noqa: E731
    if f(lo) > 0 or f(hi) < 0:
        return None
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if f(mid) < 0 else (lo, mid)
    return 0.5 * (lo + hi)


@functools.lru_cache(maxsize=8)
def concave_bridges(params: ServiceParams, z_max: float, points: int = 20001) -> tuple[Bridge, ...]:
    """Where ln S(z) departs from its convex envelope on [0, z_max]: the bridging edges of its lower hull.

    The Al-Hourani LoS probability makes ln S non-convex in z where the elevation angle changes fastest (at
    h = 100 m: horizontal distances of about 52-165 m). Off the bridges ln S equals its convex envelope, so the
    tangent there is a global lower bound; on a bridge the common tangent of its two ends is, lowered by its
    largest excess over ln S on a fine grid (zero up to rounding).

    Args:
        params: the channel constants.
        z_max: the largest squared distance of a cell to a UAV (the area's squared diagonal).
        points: grid points, evenly spaced in distance.
    """
    z = np.linspace(0.0, math.sqrt(z_max), points) ** 2
    v = log_snr_hz(z, params)
    hull = _lower_hull(z.tolist(), v.tolist())
    out = []
    for i, j in zip(hull[:-1], hull[1:]):
        chord = v[i] + (v[j] - v[i]) / (z[j] - z[i]) * (z[i + 1:j] - z[i])
        if j - i < 2 or float(np.max(v[i + 1:j] - chord)) < 1e-9:
            continue  # no point above the chord: ln S is convex there up to rounding
        za, zb = float(z[i]), float(z[j])
        for _ in range(30):  # common tangent: each end where the slope equals the chord's
            s = float((log_snr_hz(zb, params) - log_snr_hz(za, params)) / (zb - za))
            na = _slope_point(s, float(z[max(i - 4, 0)]), float(z[min(i + 4, j - 1)]), params)
            nb = _slope_point(s, float(z[max(j - 4, i + 1)]), float(z[min(j + 4, points - 1)]), params)
            if na is None or nb is None:
                break
            done = abs(na - za) + abs(nb - zb) < 1e-9 * zb
            za, zb = na, nb
            if done:
                break
        va = float(log_snr_hz(za, params))
        s = (float(log_snr_hz(zb, params)) - va) / (zb - za)
        fine = np.linspace(math.sqrt(za), math.sqrt(zb), 4001) ** 2
        excess = max(0.0, float(np.max(va + s * (fine - za) - log_snr_hz(fine, params))))
        out.append(Bridge(za=za, zb=zb, va=va - excess, slope=s))
    return tuple(out)


def log_snr_minorant(z0, params: ServiceParams, bridges: tuple[Bridge, ...]):
    """A line in z under ln S(z) for every z in [0, z_max], touching it at z0 where one can.

    Returns:
        (ln S(z0), the line's value at z0, its slope): the tangent at z0 (at Z_MIN_M2 below it), or the
        bridge's line where z0 lies on a bridge (there the value is below ln S(z0)).
    """
    z0 = np.asarray(z0, dtype=np.float64)
    zc = np.maximum(z0, Z_MIN_M2)
    vc, sc = log_snr_hz(zc, params, slope=True)
    v0 = np.where(z0 < Z_MIN_M2, log_snr_hz(z0, params), vc)
    value, slope = vc + sc * (z0 - zc), sc
    for br in bridges:
        on = (z0 > br.za) & (z0 < br.zb)
        value = np.where(on, br.va + br.slope * (z0 - br.za), value)
        slope = np.where(on, br.slope, slope)
    return v0, value, slope


def rate_surrogate(share_hz, z0, params: ServiceParams, bridges: tuple[Bridge, ...]):
    """R_lb(z) = a + b z: a lower bound of the rate at share B for every squared distance z, equal to it at z0
    (but on a bridge or below Z_MIN_M2, ``concave_bridges``); b <= 0, so a + b |q - c|^2 is concave in q.

    ln(1 + e^v / B) is convex and increasing in v = ln S, so R >= R(v0) + (B / ln 2) sigma0 (v - v0) with
    sigma0 = S0 / (B + S0); putting a line below v(z) in place of v keeps the bound. Where ln S is convex this is
    the first-order Taylor expansion of the rate in z.

    Returns:
        (a in bit/s, b in bit/s per m^2), each of the shape of the broadcast inputs.
    """
    b_hz = np.maximum(share_hz, SHARE_FLOOR_HZ)
    v0, value, slope = log_snr_minorant(z0, params, bridges)
    gain = b_hz / LN2 / (1.0 + b_hz * np.exp(-v0))  # (B / ln 2) S0 / (B + S0)
    b = gain * slope
    return shannon_rate(b_hz, v0) + gain * (value - v0) - b * z0, b


# ----------------------------------------------------------------------------------------------- slot
@dataclasses.dataclass(frozen=True, kw_only=True)
class Slot:
    """One slot's problem (float64 numpy): the observed map, the fleet and the constants."""

    x: np.ndarray
    """(G,) the observed map x_t, 0 where at or below DEMAND_EPS."""
    cells: np.ndarray
    """(G, 2) cell centres, metres."""
    start: np.ndarray
    """(K, 2) positions before the slot."""
    stay: np.ndarray
    """(K, 2) positions after the slot without a move (a returning UAV at its station)."""
    avail: np.ndarray
    """(K,) bool: serves after the slot."""
    movable: np.ndarray
    """(K,) bool: follows this slot's action and serves after it."""
    params: ServiceParams
    rotor: Rotor
    slot_s: float
    d_max_m: float
    width_m: float
    height_m: float
    weights: tuple[float, float, float]
    """(w_d, w_e, w_l)."""

    @functools.cached_property
    def has(self) -> np.ndarray:
        return self.x > 0

    @functools.cached_property
    def requested(self) -> np.ndarray:
        """(G,) q_g = x_g u r0, bit/s."""
        return self.x * self.params.demand_intensity * self.params.r0_bps

    @functools.cached_property
    def delay_weight(self) -> np.ndarray:
        """(G,) (x_g / X) q_g: the delay term is sum_g delay_weight_g / R_g."""
        return self.x / self.x.sum() * self.requested


def nearest(slot: Slot, pos: np.ndarray) -> np.ndarray:
    """(G,) the nearest available UAV of every cell (ties to the lowest index): the environment's association,
    computed by the environment's own ``dswm.sim.physics.associate``."""
    pos_t = torch.as_tensor(np.asarray(pos, dtype=np.float64))[None]
    avail_t = torch.as_tensor(np.asarray(slot.avail, dtype=bool))[None]
    return associate(pos_t, avail_t, torch.as_tensor(np.asarray(slot.cells, dtype=np.float64)))[0].numpy()


class Terms(NamedTuple):
    delay: float
    energy: float
    load: float
    total: float


def objective(slot: Slot, pos: np.ndarray, assoc: np.ndarray, share: np.ndarray) -> Terms:
    """J and its terms for positions after the slot (K, 2), an association (G,) and bandwidth shares (G,) Hz."""
    has, k = slot.has, len(pos)
    z = ((pos[assoc[has]] - slot.cells[has]) ** 2).sum(-1)
    delay = float((slot.delay_weight[has] / shannon_rate(share[has], log_snr_hz(z, slot.params))).sum())
    speed = np.linalg.norm(pos - slot.start, axis=-1)[slot.movable] / slot.slot_s
    energy = float(rotor_power(torch.as_tensor(speed), slot.rotor).sum()) / (k * hover_power(slot.rotor))
    shares = np.bincount(assoc[has], weights=slot.x[has], minlength=k)[slot.avail] / slot.x.sum()
    n = len(shares)
    load = float(n * ((shares - 1.0 / n) ** 2).sum())
    w_d, w_e, w_l = slot.weights
    return Terms(delay, energy, load, w_d * delay + w_e * energy + w_l * load)


# ----------------------------------------------------------------------------------------------- block 2
def kkt_bandwidth(weight: np.ndarray, log_snr: np.ndarray, group: np.ndarray, n_groups: int, total_hz: float,
                  *, iters: int = 40, newton: int = 30) -> np.ndarray:
    """Split ``total_hz`` over each group's cells to minimize sum_g weight_g / R_g(B_g) (KKT with bisection).

    R_g(B) = B log2(1 + S_g / B) is concave and increasing, so weight / R is convex and decreasing in B, and the
    optimum of a group is where every cell's marginal delay phi_g(B_g) = weight_g R_g'(B_g) / R_g(B_g)^2 equals
    the group's Lagrange multiplier mu, with sum_g B_g = total_hz. sum_g B_g(mu) falls in mu, so mu follows by
    bisection on ln mu; for each trial mu, B_g(mu) solves ln phi_g(B) = ln mu, which falls in ln B (safeguarded
    Newton steps from the previous trial's solution).

    Args:
        weight: (N,) weights > 0.
        log_snr: (N,) ln S_g.
        group: (N,) int group (UAV) of each cell, in [0, n_groups).
        n_groups: number of groups.
        total_hz: bandwidth of each group.
        iters: bisection steps on ln mu.
        newton: Newton steps on ln B per bisection step.

    Returns:
        (N,) shares in Hz; each group's shares sum to total_hz.
    """
    s, log_w, top = np.exp(log_snr), np.log(weight * LN2), math.log(total_hz)

    def log_phi(u):
        """ln phi at ln B = u, and its derivative in u (y = S / B, A = ln(1 + y) - y / (1 + y))."""
        y = s * np.exp(-u)
        ln1y = np.log1p(y)
        a = ln1y - y / (1.0 + y)
        value = log_w + np.log(a) - 2.0 * (u + np.log(ln1y))
        return value, -(y / (1.0 + y)) ** 2 / a - 2.0 + 2.0 * y / ((1.0 + y) * ln1y)

    def solve(log_mu, u, lo, hi):
        """ln B_g(mu) by safeguarded Newton steps inside [lo, hi]; returns it and the bracket left around it."""
        target = log_mu[group]
        for _ in range(newton):
            h, dh = log_phi(u)
            h = h - target
            grow = h > 0  # marginal delay above mu: the cell should get more
            lo, hi = np.where(grow, np.maximum(lo, u), lo), np.where(grow, hi, np.minimum(hi, u))
            if float(np.abs(h).max()) < 1e-11:
                break
            step = u - h / dh
            u = np.where((step > lo) & (step < hi), step, 0.5 * (lo + hi))
        return u, lo, hi

    # Bracket: at mu = min_g phi_g(total) every share is >= total; at max_g phi_g(total / n_k) each is <= total/n_k.
    count = np.bincount(group, minlength=n_groups)
    lo, hi = np.full(n_groups, np.inf), np.full(n_groups, -np.inf)
    np.minimum.at(lo, group, log_phi(np.full(len(s), top))[0])
    np.maximum.at(hi, group, log_phi(top - np.log(count[group]))[0])
    lo, hi = np.where(count > 0, lo, 0.0), np.where(count > 0, hi, 0.0)
    u = top - np.log(count[group])
    u_lo, u_hi = np.full(len(s), top - 60.0), np.full(len(s), top + 30.0)  # holds ln B_g(mu) for mu in [lo, hi]
    for _ in range(iters):
        mid = 0.5 * (lo + hi)
        u, at_lo, at_hi = solve(mid, np.clip(u, u_lo, u_hi), u_lo, u_hi)
        over = np.bincount(group, weights=np.exp(u), minlength=n_groups) > total_hz  # raise mu
        lo, hi = np.where(over, mid, lo), np.where(over, hi, mid)
        # B_g falls in mu: below its value at mid where mu rises from here, above it where mu falls.
        u_hi, u_lo = np.where(over[group], at_hi, u_hi), np.where(over[group], u_lo, at_lo)
    b = np.exp(solve(0.5 * (lo + hi), u, u_lo, u_hi)[0])
    return b * (total_hz / np.bincount(group, weights=b, minlength=n_groups)[group])  # exact budget


def bandwidth_block(slot: Slot, pos: np.ndarray, assoc: np.ndarray) -> np.ndarray:
    """(G,) the KKT bandwidth shares (Hz) of the cells with demand under an association; 0 elsewhere."""
    has = slot.has
    share = np.zeros(len(slot.x))
    if has.any():
        z = ((pos[assoc[has]] - slot.cells[has]) ** 2).sum(-1)
        share[has] = kkt_bandwidth(slot.delay_weight[has], log_snr_hz(z, slot.params), assoc[has], len(pos),
                                   slot.params.bandwidth_hz)
    return share


def fit_bandwidth_logit(slot: Slot, assoc: np.ndarray, share: np.ndarray) -> np.ndarray:
    """(K,) the bandwidth logit in [-1, 1] whose split x^tau (tau = e^logit) fits each UAV's KKT split best.

    The environment gives cell g of UAV k the share B x_g^tau / sum x^tau, so ln B_g = tau ln x_g + c_k: tau is
    the demand-weighted least-squares slope of ln B_g on ln x_g over the UAV's cells, and logit = ln tau clipped
    to [-1, 1] (-1 where the slope is not positive; 0 for a UAV with fewer than two cells of distinct demand).
    """
    k = len(slot.start)
    logit = np.zeros(k)
    for j in range(k):
        cell = slot.has & (assoc == j) & (share > 0)
        lx, lb, w = np.log(slot.x[cell]), np.log(share[cell]), slot.x[cell]
        if cell.sum() < 2 or np.ptp(lx) < 1e-9:
            continue
        mx, mb = np.average(lx, weights=w), np.average(lb, weights=w)
        tau = np.average((lx - mx) * (lb - mb), weights=w) / np.average((lx - mx) ** 2, weights=w)
        logit[j] = float(np.clip(math.log(tau), -1.0, 1.0)) if tau > 0 else -1.0
    return logit


# ----------------------------------------------------------------------------------------------- block 1
def _simplex_rows(a: np.ndarray) -> np.ndarray:
    """Euclidean projection of every row of ``a`` onto the probability simplex (sort-based)."""
    u = -np.sort(-a, axis=1)
    css = np.cumsum(u, axis=1) - 1.0
    idx = np.arange(1, a.shape[1] + 1)
    rho = (u - css / idx > 0).sum(axis=1)
    theta = css[np.arange(len(a)), rho - 1] / rho
    return np.maximum(a - theta[:, None], 0.0)


def association_block(slot: Slot, pos: np.ndarray, assoc: np.ndarray, *, iters: int) -> np.ndarray:
    """A new association (G,) from the relaxed problem, rounded to each cell's largest entry.

    Relaxation: a_gk in [0, 1], sum_k a_gk = 1, over the available UAVs. With cell g's rate at UAV k taken at its
    demand-proportional share there (B x_g / (load_k + x_g) for a UAV it would join), the delay is linear in a and
    the load imbalance a convex quadratic: ``iters`` projected-gradient steps (step 1 / Lipschitz constant) from the
    current association improve it. Rounding to the largest entry is the source's threshold rounding (a_gk >= 1/2
    wherever a row has such an entry).
    """
    has, av = slot.has, np.flatnonzero(slot.avail)
    x = slot.x[has]
    p, n = x / x.sum(), len(av)
    cur = assoc[has][:, None] == av[None, :]  # (Gd, n)
    load = (cur * x[:, None]).sum(0)
    z = ((slot.cells[has][:, None, :] - pos[av][None, :, :]) ** 2).sum(-1)
    share = slot.params.bandwidth_hz * x[:, None] / (load[None, :] + x[:, None] * ~cur)
    cost = slot.weights[0] * slot.delay_weight[has][:, None] / shannon_rate(share, log_snr_hz(z, slot.params))
    w_l = slot.weights[2]
    if w_l > 0 and n > 1:
        step = 1.0 / (2.0 * w_l * n * float((p * p).sum()))
        a = cur.astype(np.float64)
        for _ in range(iters):
            grad = cost + 2.0 * w_l * n * (p @ a - 1.0 / n)[None, :] * p[:, None]
            a = _simplex_rows(a - step * grad)
    else:
        a = -cost  # a linear program: each cell to its cheapest UAV
    out = assoc.copy()
    out[has] = av[a.argmax(1)]
    return out
