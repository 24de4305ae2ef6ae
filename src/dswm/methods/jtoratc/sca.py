"""JTORATC's trajectory block: the convex program of one successive-convex-approximation (SCA) step.

Around the expansion point (the current plan), each cell's rate is replaced by the concave lower bound of
``model.rate_surrogate`` (R_lb = a + b |q - c|^2, b <= 0), and the propulsion power by Zeng et al.'s upper bound:
its induced part P_i y with the slack 1 / y^2 <= y^2 + V^2 / v0^2, whose right side is replaced by its
first-order Taylor expansion (a lower bound, so the feasible y lie above the true one). The program then bounds
J from above and touches it at the expansion point: a step does not raise J where the bounds are tight (the
controller also checks the step on the exact J). The program is built once per grid with cvxpy parameters
(DPP), so a step only sets the parameters and calls the solver. Positions are in km inside the program.
"""
from __future__ import annotations

import cvxpy as cp
import numpy as np

from dswm.sim.energy import hover_power, rotor_constants
from dswm.sim.scenario import Rotor

KM = 1000.0


def induced_slack(speed_mps, rotor: Rotor):
    """y(V) = (sqrt(1 + V^4 / (4 v0^4)) - V^2 / (2 v0^2))^(1/2): the induced power is P_i y (Zeng et al.)."""
    v0 = rotor_constants(rotor)[2]
    v2 = np.asarray(speed_mps, dtype=np.float64) ** 2 / (v0 * v0)
    return np.sqrt(np.sqrt(1.0 + v2 * v2 / 4.0) - v2 / 2.0)


class TrajectoryProgram:
    """min w_d sum_g d_g / rho_g(q) + w_e E_ub(q, y) over the positions q (K, 2) after the slot.

    rho_g = alpha_g + beta_g |q_k(g) - c_g|^2 is the surrogate of cell g's rate over its request (k(g) through the
    one-hot rows of ``sel``), d_g the cell's share of the demand, and E_ub the upper bound of the propulsion energy
    over the fleet's hover power; subject to |q_k - start_k| <= radius_k (D_max, or 0 for a UAV that does not
    move), |q_k - centre_k| <= trust (the trust region around the expansion point) and q inside the area.

    Args:
        cells: (G, 2) cell centres, metres.
        n_uavs: K.
        width_m, height_m: the area.
        rotor: power model constants.
        slot_s: slot length.
        weights: (w_d, w_e).
        solver: cvxpy solver name.
    """

    def __init__(self, *, cells: np.ndarray, n_uavs: int, width_m: float, height_m: float, rotor: Rotor,
                 slot_s: float, weights: tuple[float, float], solver: str):
        g, k = len(cells), n_uavs
        p0, p_i, v0 = rotor_constants(rotor)
        blade = p0 * 3.0 / rotor.tip_speed_mps**2
        drag = 0.5 * rotor.fuselage_drag_ratio * rotor.air_density * rotor.rotor_solidity * rotor.disc_area_m2
        per_km = KM / slot_s  # speed (m/s) of a 1 km move
        self.solver, self.rotor, self.speed_per_km, self.v0 = solver, rotor, per_km, v0
        # Variables and parameters. DPP: a parameter may only multiply a parameter-free expression, hence the
        # cells' copies ``at`` of their UAV's position and the epigraph ``inv`` of their rate terms.
        self.q, self.y = cp.Variable((k, 2)), cp.Variable(k)
        at, inv = cp.Variable((g, 2)), cp.Variable(g)
        self.start, self.centre = cp.Parameter((k, 2)), cp.Parameter((k, 2))
        self.radius, self.trust = cp.Parameter(k, nonneg=True), cp.Parameter(k, nonneg=True)
        self.sel = cp.Parameter((g, k), nonneg=True)
        self.alpha, self.beta, self.demand = cp.Parameter(g), cp.Parameter(g, nonpos=True), cp.Parameter(g, nonneg=True)
        self.y0, self.move0, self.const = cp.Parameter(k, pos=True), cp.Parameter((k, 2)), cp.Parameter(k)
        # Delay: the cells' rate surrogates at their UAV's position
        z = cp.sum(cp.square(at - cells / KM), axis=1)  # km^2
        delay = self.demand @ inv
        # Energy: blade profile and parasite terms as they are (convex), induced term through Zeng's slack
        move = self.q - self.start
        speed = cp.norm(move, 2, axis=1) * per_km
        power = blade * cp.sum(cp.square(move), axis=1) * per_km**2 + p_i * self.y + drag * cp.power(speed, 3)
        energy = cp.sum(power) / (k * hover_power(rotor))
        taylor = (2.0 * cp.multiply(self.y0, self.y) + self.const  # const holds -y0^2 - (|m0|^2 + 2 m0.start) c
                  + 2.0 * per_km**2 / v0**2 * cp.sum(cp.multiply(self.move0, self.q), axis=1))
        constraints = [at == self.sel @ self.q, cp.inv_pos(self.alpha + cp.multiply(self.beta, z)) <= inv,
                       cp.norm(move, 2, axis=1) <= self.radius, cp.norm(self.q - self.centre, 2, axis=1) <= self.trust,
                       self.q >= 0, self.q[:, 0] <= width_m / KM, self.q[:, 1] <= height_m / KM,
                       cp.power(self.y, -2) <= taylor]
        self.problem = cp.Problem(cp.Minimize(weights[0] * delay + weights[1] * energy), constraints)
        assert self.problem.is_dcp(dpp=True)
        # Compile once now (seconds for a 20 x 20 grid), so that no decision's measured solve time includes it.
        for par in self.problem.parameters():
            par.value = np.ones(par.shape) * (-1.0 if par.is_nonpos() else 1.0)
        self.problem.get_problem_data(solver=solver)

    def solve(self, *, start: np.ndarray, centre: np.ndarray, radius: np.ndarray, trust: float, assoc: np.ndarray,
              alpha: np.ndarray, beta: np.ndarray, demand: np.ndarray) -> tuple[np.ndarray | None, str]:
        """One SCA step.

        Args:
            start: (K, 2) positions before the slot, metres.
            centre: (K, 2) the expansion point (the current plan), metres.
            radius: (K,) the largest move, metres (D_max for a UAV that moves, else 0).
            trust: trust-region radius, metres.
            assoc: (G,) the cell's UAV, or -1 for a cell left out (no demand, or a UAV that does not move).
            alpha, beta: (G,) the rate surrogate over the request, alpha + beta z with z in m^2.
            demand: (G,) the cell's share of the demand (0 for a cell left out).

        Returns:
            (the planned positions (K, 2) in metres, or None when the solver fails; the solver's status).
        """
        k = len(start)
        sel = np.zeros(self.sel.shape)
        sel[np.flatnonzero(assoc >= 0), assoc[assoc >= 0]] = 1.0
        out = assoc < 0
        self.sel.value = sel
        self.alpha.value = np.where(out, 1.0, alpha)
        self.beta.value = np.where(out, 0.0, np.minimum(beta, 0.0)) * KM**2
        self.demand.value = np.where(out, 0.0, demand)
        self.start.value, self.centre.value = start / KM, centre / KM
        self.radius.value, self.trust.value = np.asarray(radius, float) / KM, np.full(k, trust / KM)
        move0 = (centre - start) / KM
        y0 = induced_slack(np.linalg.norm(move0, axis=1) * self.speed_per_km, self.rotor)
        self.move0.value, self.y0.value = move0, y0
        self.const.value = (-y0**2 - ((move0**2).sum(1) + 2.0 * (move0 * start / KM).sum(1))
                            * self.speed_per_km**2 / self.v0**2)
        try:
            self.problem.solve(solver=self.solver)
        except cp.error.SolverError as exc:
            return None, f"SolverError: {exc}"
        if self.problem.status not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE) or self.q.value is None:
            return None, str(self.problem.status)
        return np.asarray(self.q.value, dtype=np.float64) * KM, str(self.problem.status)
