"""Fleet kinematics and the battery state machine of docs/PROTOCOL.md §3, as pure batched tensor functions.

The environment steps real episodes with ``fleet_step``; planners propagate imagined fleets with the very
same function, so an imagined battery return happens exactly when the environment would make it happen.

Per step of one slot (``slot_s`` seconds), for every UAV:
- active: displacement D_max * (dx, dy), norm clipped to D_max, position clipped to the area; energy
  P(V) * slot_s with V = |flown displacement| / slot_s; battery -= energy; if the battery is now below
  reserve_frac * E_batt the UAV becomes ``returning`` (it serves nothing in the next slot).
- returning: flies to its nearest station at V_max (energy P(V_max) for the flight time plus hover power for
  the rest of the slot), then becomes ``charging`` with ``recharge_slots`` slots left.
- charging: no energy; one slot fewer left; at zero it becomes active at the station with a full battery.
"""
from __future__ import annotations

import dataclasses
from typing import NamedTuple

import torch

from dswm.sim.scenario import Scenario
from dswm.sim.energy import rotor_power

ACTIVE, RETURNING, CHARGING = 0, 1, 2


@dataclasses.dataclass(frozen=True, kw_only=True)
class Geometry:
    """Service area and stations.

    Attributes:
        width_m: east-west extent of the area.
        height_m: north-south extent of the area.
    """

    width_m: float
    height_m: float

    def stations(self, dtype=torch.float32, device=None) -> torch.Tensor:
        """(4, 2) station positions: the centres of the four quadrants."""
        w, h = self.width_m, self.height_m
        return torch.tensor(
            [[w / 4, h / 4], [3 * w / 4, h / 4], [w / 4, 3 * h / 4], [3 * w / 4, 3 * h / 4]],
            dtype=dtype, device=device,
        )

    def clip(self, pos: torch.Tensor) -> torch.Tensor:
        """Clip positions (..., 2) to the area."""
        x = pos[..., 0].clamp(0.0, self.width_m)
        y = pos[..., 1].clamp(0.0, self.height_m)
        return torch.stack([x, y], dim=-1)


class FleetState(NamedTuple):
    """State of K UAVs for any leading batch shape."""

    pos: torch.Tensor
    """(..., K, 2) positions in metres."""
    battery_j: torch.Tensor
    """(..., K) remaining battery energy in joules."""
    status: torch.Tensor
    """(..., K) int64: 0 active, 1 returning, 2 charging."""
    charge_left: torch.Tensor
    """(..., K) int64 charging slots left (0 unless charging)."""

    def expand(self, n: int) -> "FleetState":
        """Repeat a single (K, ...) state into a batch of n identical states (N, K, ...)."""
        return FleetState(*(t.unsqueeze(0).expand(n, *t.shape).clone() for t in self))


def available(state: FleetState) -> torch.Tensor:
    """(..., K) bool: airborne and active, i.e. able to serve."""
    return state.status == ACTIVE


def fleet_step(state: FleetState, action: torch.Tensor, geom: Geometry,
               scenario: Scenario) -> tuple[FleetState, torch.Tensor]:
    """Advance the fleet by one slot.

    Args:
        state: current FleetState, leading shape (...).
        action: (..., K, 3) in [-1, 1]: (dx, dy, bw_logit); only (dx, dy) move the fleet here.
        geom: area and stations.
        scenario: constants (D_max, V_max, slot length, battery, reserve, recharge slots, rotor model).

    Returns:
        (next FleetState, energy spent by each UAV in joules (..., K)).
    """
    pos, battery, status, charge_left = state
    dtype = pos.dtype
    slot_s = scenario.slot_s
    is_active = status == ACTIVE
    is_returning = status == RETURNING
    is_charging = status == CHARGING

    # Active UAVs: norm-clipped displacement inside the area.
    disp = scenario.d_max_m * action[..., :2].to(dtype)
    norm = torch.linalg.vector_norm(disp, dim=-1, keepdim=True)
    disp = disp * torch.clamp(scenario.d_max_m / torch.clamp(norm, min=1e-9), max=1.0)
    moved_pos = geom.clip(pos + disp)
    speed = torch.linalg.vector_norm(moved_pos - pos, dim=-1) / slot_s
    energy_active = rotor_power(speed, scenario.rotor) * slot_s

    # Returning UAVs: to the nearest station at V_max, hover for the rest of the slot.
    stations = geom.stations(dtype=dtype, device=pos.device)
    to_station = torch.cdist(pos.reshape(-1, 2), stations).reshape(*pos.shape[:-1], stations.shape[0])
    nearest = to_station.argmin(dim=-1)
    station_pos = stations[nearest]
    fly_s = torch.clamp(to_station.gather(-1, nearest.unsqueeze(-1)).squeeze(-1) / scenario.v_max_mps,
                        max=slot_s)
    p_vmax = float(rotor_power(scenario.v_max_mps, scenario.rotor))
    p_hover = float(rotor_power(0.0, scenario.rotor))
    energy_return = p_vmax * fly_s + p_hover * (slot_s - fly_s)

    zero = torch.zeros_like(battery)
    energy = torch.where(is_active, energy_active, torch.where(is_returning, energy_return, zero))
    new_pos = torch.where(is_active.unsqueeze(-1), moved_pos,
                          torch.where(is_returning.unsqueeze(-1), station_pos, pos))
    new_battery = battery - energy

    # State machine.
    depleted = is_active & (new_battery < scenario.reserve_frac * scenario.battery_j)
    left_after = charge_left - 1
    recharged = is_charging & (left_after <= 0)
    new_status = torch.where(depleted, torch.full_like(status, RETURNING), status)
    new_status = torch.where(is_returning, torch.full_like(status, CHARGING), new_status)
    new_status = torch.where(recharged, torch.full_like(status, ACTIVE), new_status)
    new_charge_left = torch.where(is_returning, torch.full_like(charge_left, scenario.recharge_slots),
                                  torch.where(is_charging, torch.clamp(left_after, min=0), charge_left))
    new_battery = torch.where(recharged, torch.full_like(new_battery, scenario.battery_j), new_battery)
    return FleetState(new_pos, new_battery, new_status, new_charge_left), energy
