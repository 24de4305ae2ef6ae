"""Rotor power against the published model constants and hand-derived values."""
import math

import pytest
import torch

from dswm.sim.energy import hover_power, rotor_constants, rotor_power, slot_energy
from dswm.sim.scenario import load_scenario

from conftest import ROOT

ROTOR = load_scenario(ROOT / "config.yaml").rotor  # the published model constants (docs/PROTOCOL.md §1)


def test_model_constants_by_hand():
    # P0 = delta/8 * rho * s * A * Omega^3 * R^3 ; Pi = (1+k) W^1.5 / sqrt(2 rho A)
    p0, pi, v0 = rotor_constants(ROTOR)
    assert p0 == pytest.approx(0.012 / 8 * 1.225 * 0.05 * 0.503 * 300**3 * 0.4**3, rel=1e-12)
    assert p0 == pytest.approx(79.856, abs=1e-3)
    assert pi == pytest.approx(88.628, abs=1e-3)
    assert v0 == pytest.approx(math.sqrt(20 / (2 * 1.225 * 0.503)), rel=1e-12)
    assert v0 == pytest.approx(4.0285, abs=1e-4)


def test_hover_power_is_published_value():
    assert hover_power(ROTOR) == pytest.approx(168.48, abs=0.01)
    assert slot_energy(0.0, 600.0, ROTOR) == pytest.approx(101_090, abs=2)


@pytest.mark.parametrize("speed", [2.5, 10.0, 25.0])
def test_power_at_speed_by_hand(speed):
    p0, pi, v0 = 79.85628, 88.62793, 4.028535
    blade = p0 * (1 + 3 * speed**2 / 120**2)
    induced = pi * math.sqrt(math.sqrt(1 + speed**4 / (4 * v0**4)) - speed**2 / (2 * v0**2))
    parasite = 0.5 * 0.6 * 1.225 * 0.05 * 0.503 * speed**3
    assert rotor_power(speed, ROTOR) == pytest.approx(blade + induced + parasite, rel=1e-5)


def test_tensor_and_float_agree_and_minimum_is_near_cruise():
    v = torch.linspace(0, 30, 301, dtype=torch.float64)
    p = rotor_power(v, ROTOR)
    assert p.shape == v.shape
    assert float(p[100]) == pytest.approx(rotor_power(10.0, ROTOR), rel=1e-12)
    # The rotary-wing curve first falls (induced power) then rises (parasite power): minimum in 5..20 m/s.
    v_min = float(v[p.argmin()])
    assert 5.0 < v_min < 20.0
    assert float(p.min()) < hover_power(ROTOR) < rotor_power(25.0, ROTOR)
