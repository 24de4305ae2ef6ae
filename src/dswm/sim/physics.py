"""The service model of docs/PROTOCOL.md §2: the ONE implementation used by the environment, every planner and
the world model's decomposed service head.

Chain for a batch of N candidate fleets, K UAVs and G cells:
nearest-available association (distances for every (candidate, cell, UAV), no transcendental work; a
compiled kernel on CPU, ``dswm.sim.kernels``)
-> elevation angle, Al-Hourani LoS probability and dB-mixed path loss for the ASSOCIATED pair only
-> per-UAV bandwidth split with weights x_g^tau_k, tau_k = exp(bw_logit_k)
-> Shannon rate -> capped fulfilment f_g = min(1, R_g / (x_g u r0)) -> served ratio sum x f / sum x.

Association is hard (argmin); gradients reach the UAV positions through the associated pair's distance and
reach the demand through the bandwidth shares and the fulfilment, which is what a planner or a world model
needs. Everything is batched over the leading candidate axis.
"""
from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import torch

from dswm.sim.scenario import Scenario
from dswm.sim.kernels import nearest_available

SPEED_OF_LIGHT_MPS = 299_792_458.0
# Demand below this (in normalized units, i.e. a 1e-9 fraction of the training p99) counts as no demand:
# it keeps x^tau and the bandwidth shares finite in float32 and changes no served ratio measurably.
DEMAND_EPS = 1e-9
# In the Shannon rate a share below 1 mHz counts as 1 mHz. Such shares only go to cells whose demand is a
# tiny fraction of their UAV's (x^tau weights), whose fulfilment is ~0 either way; the floor keeps the rate's
# gradient finite in float32 (d/dB of B log2(1 + c/B) involves c/B^2).
SHARE_FLOOR_HZ = 1e-3


@dataclasses.dataclass(frozen=True, kw_only=True)
class ServiceParams:
    """Constants of the service model (a projection of the Scenario; their values live in config.yaml only)."""

    altitude_m: float
    carrier_hz: float
    bandwidth_hz: float
    tx_power_w: float
    noise_psd_w_per_hz: float
    r0_bps: float
    demand_intensity: float
    u_peak: float
    los_a: float
    los_b: float
    eta_los_db: float
    eta_nlos_db: float

    @classmethod
    def from_scenario(cls, scenario: Scenario) -> "ServiceParams":
        """Take the service constants out of a Scenario."""
        return cls(
            altitude_m=scenario.altitude_m,
            carrier_hz=scenario.carrier_hz,
            bandwidth_hz=scenario.bandwidth_hz,
            tx_power_w=scenario.tx_power_w,
            noise_psd_w_per_hz=scenario.noise_psd_w_per_hz,
            r0_bps=scenario.r0_bps,
            demand_intensity=scenario.intensity,
            u_peak=scenario.u_peak,
            los_a=scenario.channel.a,
            los_b=scenario.channel.b,
            eta_los_db=scenario.channel.eta_los_db,
            eta_nlos_db=scenario.channel.eta_nlos_db,
        )


class ServiceResult(NamedTuple):
    """Per-candidate outcome of one slot of service."""

    sr: torch.Tensor
    """(N,) served ratio."""
    fulfilment: torch.Tensor
    """(N, G) capped fulfilment f_g (0 for cells without demand or without a UAV)."""
    assoc: torch.Tensor
    """(N, G) int64 index of the serving UAV (meaningless where no UAV is available)."""
    rate_bps: torch.Tensor
    """(N, G) Shannon rate of the cell's link (0 for cells without demand)."""
    share_hz: torch.Tensor
    """(N, G) bandwidth given to the cell."""


_LN10_OVER_10 = math.log(10.0) / 10.0


def _snr_hz_constant(params: ServiceParams) -> float:
    """(P / N0) * (c / (4 pi f))^2: SNR x bandwidth at 1 m^2 squared distance, before the excess loss."""
    wavelength_over_4pi = SPEED_OF_LIGHT_MPS / (4.0 * math.pi * params.carrier_hz)
    return params.tx_power_w / params.noise_psd_w_per_hz * wavelength_over_4pi**2


def los_probability(theta_deg, a: float, b: float):
    """LoS probability 1 / (1 + a exp(-b (theta - a))) with the elevation angle in DEGREES.

    Args:
        theta_deg: float or tensor of elevation angles in degrees.
        a, b: Al-Hourani environment constants (urban defaults).

    Returns:
        Same type and shape as ``theta_deg``.
    """
    if isinstance(theta_deg, torch.Tensor):
        return torch.sigmoid(b * (theta_deg - a) - math.log(a))
    return 1.0 / (1.0 + a * math.exp(-b * (float(theta_deg) - a)))


def elevation_deg(distance_m, altitude_m: float, *, horizontal_sq=None):
    """Elevation angle arcsin(h / d) in degrees (tensor or float).

    For tensors the angle is computed as atan(h / horizontal distance), with the horizontal distance squared
    floored at 1e-12 m^2: the angle is a cone over the cell centre, and right above it the floor gives the
    zero subgradient instead of the infinite slope of arcsin at 1 (which would turn gradients into NaN).

    Args:
        distance_m: 3-D link distance (may be None for tensors when ``horizontal_sq`` is given).
        altitude_m: flight altitude h.
        horizontal_sq: optional squared horizontal distance (tensors only; avoids d^2 - h^2 cancellation).
    """
    if isinstance(distance_m, torch.Tensor) or horizontal_sq is not None:
        if horizontal_sq is None:
            horizontal_sq = distance_m * distance_m - altitude_m**2
        horizontal = torch.sqrt(torch.clamp(horizontal_sq, min=1e-12))
        return torch.atan(altitude_m / horizontal) * (180.0 / math.pi)
    return math.degrees(math.asin(min(1.0, altitude_m / float(distance_m))))


def path_loss_db(distance_m, params: ServiceParams, *, horizontal_sq=None):
    """Expected path loss in dB: free space plus LoS/NLoS excess losses mixed in dB (paper eq. 2).

    Args:
        distance_m: 3-D link distance, float or tensor.
        params: channel constants.
        horizontal_sq: optional squared horizontal distance of the same links (tensors only).

    Returns:
        Path loss in dB, same type and shape as the input.
    """
    theta = elevation_deg(distance_m, params.altitude_m, horizontal_sq=horizontal_sq)
    p_los = los_probability(theta, params.los_a, params.los_b)
    fspl_k = 20.0 * math.log10(4.0 * math.pi * params.carrier_hz / SPEED_OF_LIGHT_MPS)
    if isinstance(distance_m, torch.Tensor):
        fspl = fspl_k + 20.0 * torch.log10(distance_m)
    else:
        fspl = fspl_k + 20.0 * math.log10(float(distance_m))
    return fspl + p_los * params.eta_los_db + (1.0 - p_los) * params.eta_nlos_db


def associate(pos: torch.Tensor, available: torch.Tensor, cells: torch.Tensor) -> torch.Tensor:
    """Nearest available UAV of every cell by horizontal distance.

    Args:
        pos: (N, K, 2) UAV positions in metres.
        available: (N, K) bool, airborne and active.
        cells: (G, 2) cell centres in metres.

    Returns:
        (N, G) int64 index of the nearest available UAV (0 where none is available). Ties go to the lowest
        UAV index. Not differentiable (an index): gradients reach positions through the associated pair.
    """
    return nearest_pairs(pos, available, cells)[0]


def nearest_pairs(pos: torch.Tensor, available: torch.Tensor,
                  cells: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``associate`` and the squared horizontal distance of every cell to its UAV (N, G), not differentiable.

    On CPU the compiled kernel ``dswm.sim.kernels.nearest_available`` does it in one pass per candidate; on other
    devices ``nearest_pairs_tensor`` does. Both compute the squared distance the same way and agree exactly.
    """
    if pos.device.type == "cpu":
        return nearest_available(pos, available, cells)
    return nearest_pairs_tensor(pos, available, cells)


def nearest_pairs_tensor(pos: torch.Tensor, available: torch.Tensor,
                         cells: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``nearest_pairs`` with tensor operations over the (N, K, G) distances (any device; same arguments)."""
    with torch.no_grad():
        p = pos.detach()
        c = cells.to(p.dtype)
        dx = c[:, 0].view(1, 1, -1) - p[..., 0:1]                           # (N, K, G) cell minus UAV
        dy = c[:, 1].view(1, 1, -1) - p[..., 1:2]
        d2 = dx * dx + dy * dy
        idx = d2.masked_fill(~available.unsqueeze(-1), float("inf")).argmin(dim=1)   # first minimum
        return idx, torch.gather(d2, 1, idx.unsqueeze(1)).squeeze(1)


def sum_per_uav(values: torch.Tensor, assoc: torch.Tensor, k: int) -> torch.Tensor:
    """Sum of ``values`` (N, G) over the cells each of the K UAVs serves (``assoc`` (N, G)): (N, K)."""
    return torch.zeros(values.shape[0], k, dtype=values.dtype, device=values.device).scatter_add(1, assoc, values)


def _above(x: torch.Tensor, threshold: float) -> torch.Tensor:
    """Float mask (1.0 / 0.0) of x > threshold, not differentiable. Float masks, not bool ones: on CPU a
    comparison written into a float tensor, and products with it, cost a fraction of bool masks and where()."""
    return torch.gt(x.detach(), threshold, out=torch.empty(x.shape, dtype=x.dtype, device=x.device))


def service(
    demand: torch.Tensor,
    pos: torch.Tensor,
    available: torch.Tensor,
    cells: torch.Tensor,
    *,
    params: ServiceParams,
    bw_logit: torch.Tensor | None = None,
) -> ServiceResult:
    """Serve one slot of demand with N candidate fleets.

    Args:
        demand: (N, G) or (G,) non-negative normalized demand x_g.
        pos: (N, K, 2) UAV positions in metres.
        available: (N, K) bool, UAVs that are airborne and active (not returning, not charging).
        cells: (G, 2) cell centres in metres.
        params: service constants.
        bw_logit: (N, K) bandwidth logits in [-1, 1], or None for the demand-proportional split (logit 0).

    Returns:
        ServiceResult with sr (N,), fulfilment/assoc/rate_bps/share_hz (N, G).

    Cells without demand are handled with 0/1 float masks (``has``, ``hasnt``) instead of where(): every
    guarded quantity stays finite (log of 1, shares floored), and multiplying by the mask zeroes its value
    and its gradient.
    """
    n, k, _ = pos.shape
    x = demand.to(pos.dtype)
    if x.dim() == 1:
        x = x.unsqueeze(0)
    x = x.expand(n, -1)
    has = _above(x, DEMAND_EPS)                        # (N, G) 1.0 where the cell has demand
    x = x * has
    hasnt = 1.0 - has
    x_safe = x + hasnt                                 # 1 where the cell has no demand
    assoc, horiz2 = nearest_pairs(pos, available, cells)  # (N, G)

    # Channel of the associated pair only: O(N*G) transcendental work. The linear gain 10^(-PL/10) of
    # ``path_loss_db`` is written as (lambda / 4 pi)^2 / d^2 * 10^(-excess/10): no log10 and no pow per pair.
    if pos.requires_grad and torch.is_grad_enabled():
        # The same squared distance, differentiable in the serving UAV's position.
        c = cells.to(pos.dtype)
        dx = torch.gather(pos[..., 0], 1, assoc) - c[:, 0]  # (N, G) serving UAV minus cell centre
        dy = torch.gather(pos[..., 1], 1, assoc) - c[:, 1]
        horiz2 = dx * dx + dy * dy
    dist2 = horiz2 + params.altitude_m**2
    theta = elevation_deg(None, params.altitude_m, horizontal_sq=horiz2)
    p_los = los_probability(theta, params.los_a, params.los_b)
    excess_db = params.eta_nlos_db + p_los * (params.eta_los_db - params.eta_nlos_db)
    # (P / N0) first: N0 * B underflows float32 for small shares.
    snr_hz = _snr_hz_constant(params) * torch.exp(excess_db * (-_LN10_OVER_10)) / dist2  # SNR x bandwidth

    # Bandwidth split over the UAV's associated cells with weights x^tau (zero-demand cells get nothing).
    if bw_logit is None:
        weight = x
    else:
        tau = torch.gather(torch.exp(bw_logit.to(pos.dtype)), 1, assoc)   # exp on (N, K), then per cell
        weight = torch.exp(tau * torch.log(x_safe)) * has
    weight_sum = sum_per_uav(weight, assoc, k)
    # A cell with demand has weight >= 1e-9^e > 0 in its own UAV's sum; a UAV whose cells have none has sum 0
    # and shares 0 / tiny = 0.
    denom = torch.gather(weight_sum, 1, assoc).clamp_min(torch.finfo(pos.dtype).tiny)
    share = params.bandwidth_hz * weight / denom
    share_safe = share.clamp(min=SHARE_FLOOR_HZ)

    # Shannon rate and capped fulfilment.
    rate = share_safe * torch.log2(1.0 + snr_hz / share_safe) * has
    requested = x_safe * (params.demand_intensity * params.r0_bps)
    fulfil = torch.clamp(rate / requested, max=1.0)  # 0 without demand: rate 0 over requested r0

    any_available = available.any(dim=-1)  # (N,)
    fulfil = fulfil * any_available.unsqueeze(-1).to(fulfil.dtype)
    total = x.sum(-1)
    served = (x * fulfil).sum(-1)
    sr = torch.where(total > 0, served / torch.where(total > 0, total, torch.ones_like(total)),
                     torch.ones_like(total))
    sr = torch.where(any_available, sr, torch.zeros_like(sr))
    return ServiceResult(sr=sr, fulfilment=fulfil, assoc=assoc, rate_bps=rate, share_hz=share)


def served_ratio(
    demand: torch.Tensor,
    pos: torch.Tensor,
    available: torch.Tensor,
    cells: torch.Tensor,
    *,
    params: ServiceParams,
    bw_logit: torch.Tensor | None = None,
) -> torch.Tensor:
    """Served ratio SR = sum_g x_g f_g / sum_g x_g of N candidate fleets (paper eq. 6).

    Args: as ``service``.

    Returns:
        (N,) served ratio in [0, 1]; 1 where the slot has no demand, 0 where no UAV is available.
    """
    return service(demand, pos, available, cells, params=params, bw_logit=bw_logit).sr


def jain_index(fulfilment: torch.Tensor, demand: torch.Tensor, u_peak: float) -> torch.Tensor:
    """Jain index over demand-carrying cells of f~ (f~ = 1 where f >= U_peak, else f).

    Args:
        fulfilment: (N, G) capped fulfilment.
        demand: (N, G) or (G,) demand; cells with zero demand are left out.
        u_peak: satisfaction threshold.

    Returns:
        (N,) Jain index in (0, 1]; 1 where no cell carries demand.
    """
    mask = (demand > 0).expand_as(fulfilment).to(fulfilment.dtype)
    f = torch.where(fulfilment >= u_peak, torch.ones_like(fulfilment), fulfilment) * mask
    n = mask.sum(-1)
    s1 = f.sum(-1)
    s2 = (f * f).sum(-1)
    ok = (n > 0) & (s2 > 0)
    jain = s1 * s1 / torch.where(ok, n * s2, torch.ones_like(s2))
    return torch.where(ok, jain, torch.where(n > 0, torch.zeros_like(s2), torch.ones_like(s2)))
