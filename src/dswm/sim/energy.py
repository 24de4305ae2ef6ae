"""Rotary-wing propulsion power (Zeng, Xu, Zhang 2019) and per-slot energy.

P(V) = P0 (1 + 3 V^2 / U_tip^2) + Pi (sqrt(1 + V^4 / (4 v0^4)) - V^2 / (2 v0^2))^(1/2) + 1/2 d0 rho s A V^3,
with P0 = (delta/8) rho s A Omega^3 R^3, Pi = (1 + k) W^1.5 / sqrt(2 rho A), v0 = sqrt(W / (2 rho A)).
"""
from __future__ import annotations

import math

import torch

from dswm.sim.scenario import Rotor

def rotor_constants(rotor: Rotor) -> tuple[float, float, float]:
    """Blade-profile hover power P0 (W), induced hover power Pi (W) and mean induced velocity v0 (m/s)."""
    rho, s, area = rotor.air_density, rotor.rotor_solidity, rotor.disc_area_m2
    p0 = rotor.profile_drag_coefficient / 8.0 * rho * s * area
    p0 *= rotor.blade_angular_velocity**3 * rotor.rotor_radius_m**3
    pi = (1.0 + rotor.induced_power_correction) * rotor.weight_n**1.5 / math.sqrt(2.0 * rho * area)
    v0 = math.sqrt(rotor.weight_n / (2.0 * rho * area))
    return p0, pi, v0


def rotor_power(speed_mps, rotor: Rotor):
    """Propulsion power at horizontal speed V.

    Args:
        speed_mps: float or tensor of speeds (m/s), any shape.
        rotor: model constants.

    Returns:
        Power in watts, a float for a float input, else a tensor of the input's shape.
    """
    p0, pi, v0 = rotor_constants(rotor)
    blade_k = 3.0 / rotor.tip_speed_mps**2
    drag_k = 0.5 * rotor.fuselage_drag_ratio * rotor.air_density * rotor.rotor_solidity * rotor.disc_area_m2
    if isinstance(speed_mps, torch.Tensor):
        v2 = speed_mps * speed_mps
        induced = torch.sqrt(torch.sqrt(1.0 + v2 * v2 / (4.0 * v0**4)) - v2 / (2.0 * v0**2))
        return p0 * (1.0 + blade_k * v2) + pi * induced + drag_k * v2 * speed_mps
    v = float(speed_mps)
    v2 = v * v
    induced = math.sqrt(math.sqrt(1.0 + v2 * v2 / (4.0 * v0**4)) - v2 / (2.0 * v0**2))
    return p0 * (1.0 + blade_k * v2) + pi * induced + drag_k * v2 * v


def hover_power(rotor: Rotor) -> float:
    """P(0) in watts (about 168.48 W with the published constants)."""
    return float(rotor_power(0.0, rotor))


def slot_energy(speed_mps, slot_s: float, rotor: Rotor):
    """Energy (J) of flying a whole slot of ``slot_s`` seconds at constant speed ``speed_mps``."""
    return rotor_power(speed_mps, rotor) * slot_s
