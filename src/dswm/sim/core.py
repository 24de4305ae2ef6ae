"""Batched fleet environment core: many one-day episodes stepped at once on a demand tensor.

Timing (docs/PROTOCOL.md §3): at slot t the controller sees o_t (maps x_{t-w..t}, fleet state, time phase) and
acts; the fleet moves to p_{t+1}; x_{t+1} is revealed and SR_{t+1} = SR(x_{t+1}, p_{t+1}). Slot 0 is served
by the initial deployment, SR_0 = SR(x_0, p_0) with the demand-proportional split, so a day has T-1 decisions
and T served-ratio values; its score is their mean.
"""
from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple, Sequence

import numpy as np
import torch

from dswm.config import stable_hash
from dswm.sim.scenario import Scenario
from dswm.sim.energy import hover_power
from dswm.sim.fleet import ACTIVE, CHARGING, RETURNING, FleetState, Geometry, available, fleet_step
from dswm.sim.physics import ServiceParams, jain_index, service, sum_per_uav

OBS_SPEC_VERSION = 1
FLEET_FEATURES = ("x_over_width", "y_over_height", "battery_fraction", "active", "returning", "charging",
                  "charge_left_over_recharge_slots")


@dataclasses.dataclass(frozen=True, kw_only=True)
class Grid:
    """A dataset grid: ``rows x cols`` cells of side ``cell_m``; row 0 south, column 0 west."""

    rows: int
    cols: int
    cell_m: float

    @property
    def n_cells(self) -> int:
        return self.rows * self.cols

    def geometry(self) -> Geometry:
        """Area and stations of this grid."""
        return Geometry(width_m=self.cols * self.cell_m, height_m=self.rows * self.cell_m)

    def cells(self, dtype=torch.float32, device=None) -> torch.Tensor:
        """(G, 2) cell centres in metres, flattened row-major (g = row * cols + col)."""
        r, c = torch.meshgrid(torch.arange(self.rows, dtype=torch.float64),
                              torch.arange(self.cols, dtype=torch.float64), indexing="ij")
        xy = torch.stack([(c + 0.5) * self.cell_m, (r + 0.5) * self.cell_m], dim=-1).reshape(-1, 2)
        return xy.to(dtype=dtype, device=device)


def obs_spec(grid: Grid, scenario: Scenario) -> dict:
    """The observation specification (shapes and meaning) shared by every method."""
    return {
        "version": OBS_SPEC_VERSION,
        "demand": {"shape": [scenario.obs_window + 1, grid.rows, grid.cols],
                   "content": "normalized demand x_{t-w..t}, edge-padded with the day's first map"},
        "fleet": {"shape": [scenario.n_uavs, len(FLEET_FEATURES)], "features": list(FLEET_FEATURES),
                  "recharge_slots": scenario.recharge_slots},
        "time": {"shape": [2], "content": "sin, cos of 2*pi*slot/slots_per_day",
                 "slots_per_day": scenario.slots_per_day},
    }


def obs_spec_hash(grid: Grid, scenario: Scenario) -> str:
    """Hash of the observation specification; recorded with every result file."""
    return stable_hash(obs_spec(grid, scenario))


def validate_demand(demand: np.ndarray, grid: Grid, scenario: Scenario, *, where: str = "demand") -> None:
    """Raise ValueError naming the problem when a demand tensor is not (days, T, rows, cols), finite, >= 0."""
    if not isinstance(demand, np.ndarray):
        raise ValueError(f"{where}: expected a numpy array, found {type(demand).__name__}")
    expected = ("days", scenario.slots_per_day, grid.rows, grid.cols)
    if demand.ndim != 4 or tuple(demand.shape[1:]) != expected[1:] or demand.shape[0] < 1:
        raise ValueError(f"{where}: expected shape {expected}, found {tuple(demand.shape)}")
    bad = ~np.isfinite(demand)
    if bad.any():
        d, t, r, c = np.argwhere(bad)[0]
        raise ValueError(f"{where}: non-finite value {demand[d, t, r, c]} at day {d}, slot {t}, row {r}, col {c}")
    if (demand < 0).any():
        d, t, r, c = np.argwhere(demand < 0)[0]
        raise ValueError(f"{where}: negative demand {demand[d, t, r, c]} at day {d}, slot {t}, row {r}, col {c}")


def initial_positions(train_mean_map: np.ndarray, grid: Grid, n_uavs: int, seed: int) -> np.ndarray:
    """Demand-weighted K-means of the mean TRAINING map (docs/PROTOCOL.md §3).

    Args:
        train_mean_map: (rows, cols) mean demand over the training days.
        grid: dataset grid.
        n_uavs: K.
        seed: K-means seed.

    Returns:
        (K, 2) float32 positions in metres.
    """
    from sklearn.cluster import KMeans

    weights = np.asarray(train_mean_map, dtype=np.float64).reshape(-1)
    if weights.shape[0] != grid.n_cells or not np.isfinite(weights).all() or (weights < 0).any():
        raise ValueError(f"train_mean_map: expected ({grid.rows}, {grid.cols}) finite non-negative values, "
                         f"found shape {np.shape(train_mean_map)}")
    if (weights > 0).sum() < n_uavs:
        weights = weights + 1e-6 * max(weights.max(), 1.0)
    cells = grid.cells(dtype=torch.float64).numpy()
    km = KMeans(n_clusters=n_uavs, random_state=seed, n_init=10).fit(cells, sample_weight=weights)
    centres = km.cluster_centers_[np.lexsort((km.cluster_centers_[:, 0], km.cluster_centers_[:, 1]))]
    return centres.astype(np.float32)


def initial_batteries(dataset: str, day_label: str, scenario: Scenario) -> np.ndarray:
    """Batteries evenly spaced over [low, high] * E_batt, permuted by a draw from (dataset, day) alone.

    Returns:
        (K,) float64 battery energies in joules.
    """
    k = scenario.n_uavs
    levels = np.linspace(scenario.init.battery_low_frac, scenario.init.battery_high_frac, k) * scenario.battery_j
    seed = int(stable_hash({"dataset": dataset, "day": str(day_label)}), 16)
    return levels[np.random.default_rng(seed).permutation(k)]


def build_observation(window: torch.Tensor, state: FleetState, slot: torch.Tensor, grid: Grid,
                      scenario: Scenario) -> dict[str, np.ndarray]:
    """The observation of every method (spec: ``obs_spec``).

    Args:
        window: (B, w+1, rows, cols) demand maps x_{t-w..t}.
        state: fleet state with leading shape (B,).
        slot: (B,) int64 slot index t.
        grid, scenario: geometry and constants.

    Returns:
        dict of float32 numpy arrays: demand (B, w+1, rows, cols), fleet (B, K, 7), time (B, 2).
    """
    geom = grid.geometry()
    status = state.status
    fleet = torch.stack([
        state.pos[..., 0] / geom.width_m,
        state.pos[..., 1] / geom.height_m,
        state.battery_j / scenario.battery_j,
        (status == ACTIVE).to(state.pos.dtype),
        (status == RETURNING).to(state.pos.dtype),
        (status == CHARGING).to(state.pos.dtype),
        state.charge_left.to(state.pos.dtype) / scenario.recharge_slots,
    ], dim=-1)
    phase = 2.0 * math.pi * slot.to(torch.float64) / scenario.slots_per_day
    time = torch.stack([torch.sin(phase), torch.cos(phase)], dim=-1)
    return {"demand": window.float().numpy(), "fleet": fleet.float().numpy(), "time": time.float().numpy()}


def fleet_state_from_obs(fleet_obs, grid: Grid, scenario: Scenario) -> FleetState:
    """Recover the fleet state from the ``fleet`` part of an observation (..., K, 7)."""
    f = torch.as_tensor(np.asarray(fleet_obs), dtype=torch.float64)
    geom = grid.geometry()
    pos = torch.stack([f[..., 0] * geom.width_m, f[..., 1] * geom.height_m], dim=-1)
    status = f[..., 3:6].argmax(dim=-1)
    charge_left = torch.round(f[..., 6] * scenario.recharge_slots).long()
    return FleetState(pos.float(), (f[..., 2] * scenario.battery_j).float(), status, charge_left)


class StepOutput(NamedTuple):
    obs: dict
    reward: np.ndarray  # (B,)
    sr: np.ndarray  # (B,) SR_{t+1}
    energy_j: np.ndarray  # (B,) fleet energy of the slot
    jain: np.ndarray  # (B,)
    terminated: np.ndarray  # (B,) bool, always False: no state of the fleet ends its task
    truncated: np.ndarray  # (B,) bool, the day is over: the episode is cut by time, so a TD target bootstraps


class FleetCore:
    """Steps B one-day episodes at once. All episodes of a batch advance slot by slot together."""

    def __init__(self, *, demand: np.ndarray, grid: Grid, scenario: Scenario, init_pos: np.ndarray,
                 dataset: str, day_labels: Sequence[str], device: str = "cpu"):
        validate_demand(demand, grid, scenario)
        if len(day_labels) != demand.shape[0]:
            raise ValueError(f"day_labels: expected {demand.shape[0]} labels, found {len(day_labels)}")
        init_pos = np.asarray(init_pos, dtype=np.float32)
        if init_pos.shape != (scenario.n_uavs, 2) or not np.isfinite(init_pos).all():
            raise ValueError(f"init_pos: expected finite ({scenario.n_uavs}, 2), found {init_pos.shape}")
        self.grid, self.scenario, self.dataset = grid, scenario, dataset
        self.day_labels = [str(d) for d in day_labels]
        self.device = torch.device(device)
        self.demand = torch.as_tensor(demand, dtype=torch.float32, device=self.device).reshape(
            demand.shape[0], demand.shape[1], grid.n_cells)
        self.geom = grid.geometry()
        self.cells = grid.cells(device=self.device)
        self.params = ServiceParams.from_scenario(scenario)
        self.init_pos = self.geom.clip(torch.as_tensor(init_pos, device=self.device))
        self.hover_energy_j = hover_power(scenario.rotor) * scenario.slot_s
        self.days = torch.zeros(0, dtype=torch.long)
        self.t = 0

    @property
    def n_days(self) -> int:
        return int(self.demand.shape[0])

    @property
    def uav_load(self) -> np.ndarray:
        """(B, K) demand each UAV served in the current slot (sum of x_g f_g over its associated cells): the
        per-UAV load that fairness-regularized learners read after ``reset``/``step``."""
        x, res = self._served
        with torch.no_grad():
            return sum_per_uav(x * res.fulfilment, res.assoc, self.scenario.n_uavs).numpy()

    def _window(self) -> torch.Tensor:
        w = self.scenario.obs_window
        idx = torch.clamp(torch.arange(self.t - w, self.t + 1, device=self.device), min=0)
        maps = self.demand[self.days.unsqueeze(1), idx.unsqueeze(0)]  # (B, w+1, G)
        return maps.reshape(len(self.days), w + 1, self.grid.rows, self.grid.cols)

    def observe(self) -> dict[str, np.ndarray]:
        """Observation of the current slot for every episode of the batch."""
        slot = torch.full((len(self.days),), self.t, dtype=torch.long)
        return build_observation(self._window(), self.state, slot, self.grid, self.scenario)

    def reset(self, days: Sequence[int]) -> dict[str, np.ndarray]:
        """Start one episode per entry of ``days`` (tensor day indices) at slot 0.

        Returns:
            The batched observation o_0; ``self.sr0`` holds SR_0 (B,) of the initial deployment.
        """
        days = torch.as_tensor(np.asarray(days, dtype=np.int64), device=self.device)
        if days.ndim != 1 or len(days) == 0 or days.min() < 0 or days.max() >= self.n_days:
            raise ValueError(f"days: expected a non-empty list of indices in [0, {self.n_days}), found {days.tolist()}")
        b, k = len(days), self.scenario.n_uavs
        battery = np.stack([initial_batteries(self.dataset, self.day_labels[d], self.scenario) for d in days.tolist()])
        self.days, self.t = days, 0
        self.state = FleetState(
            pos=self.init_pos.unsqueeze(0).expand(b, k, 2).clone(),
            battery_j=torch.as_tensor(battery, dtype=torch.float32, device=self.device),
            status=torch.full((b, k), ACTIVE, dtype=torch.long, device=self.device),
            charge_left=torch.zeros((b, k), dtype=torch.long, device=self.device),
        )
        res = self._serve(self.demand[self.days, 0], self.state, None)
        self.sr0 = res.sr.numpy()
        self._served = (self.demand[self.days, 0], res)
        self.jain0 = jain_index(res.fulfilment, self.demand[self.days, 0], self.scenario.u_peak).numpy()
        return self.observe()

    def _serve(self, x: torch.Tensor, state: FleetState, bw_logit):
        with torch.no_grad():
            return service(x, state.pos, available(state), self.cells, params=self.params, bw_logit=bw_logit)

    def check_action(self, action) -> torch.Tensor:
        """(B, K, 3) finite action, clipped to [-1, 1]; NaN/inf or a wrong shape raise ValueError."""
        a = torch.as_tensor(np.asarray(action, dtype=np.float32), device=self.device)
        expected = (len(self.days), self.scenario.n_uavs, 3)
        if tuple(a.shape) != expected:
            raise ValueError(f"action: expected shape {expected}, found {tuple(a.shape)}")
        if not torch.isfinite(a).all():
            b, k, j = torch.nonzero(~torch.isfinite(a))[0].tolist()
            raise ValueError(f"action: non-finite value {a[b, k, j].item()} at episode {b}, UAV {k}, component {j}")
        return a.clamp(-1.0, 1.0)

    def step(self, action) -> StepOutput:
        """Apply one action per episode, move to slot t+1 and serve x_{t+1}."""
        if self.t >= self.scenario.slots_per_day - 1:
            raise RuntimeError("step() after the end of the day: call reset() first")
        a = self.check_action(action)
        with torch.no_grad():
            self.state, energy = fleet_step(self.state, a, self.geom, self.scenario)
            self.t += 1
            x = self.demand[self.days, self.t]
            res = self._serve(x, self.state, a[..., 2])
            jain = jain_index(res.fulfilment, x, self.scenario.u_peak)
            self._served = (x, res)  # for uav_load, computed only when a learner asks
            fleet_energy = energy.sum(-1)
            s = self.scenario
            reward = res.sr - s.reward_beta * (1.0 - res.sr) - s.reward_alpha * fleet_energy / (
                self.hover_energy_j * s.n_uavs)
        done = self.t >= s.slots_per_day - 1
        b = len(self.days)
        return StepOutput(obs=self.observe(), reward=reward.numpy(), sr=res.sr.numpy(),
                          energy_j=fleet_energy.numpy(), jain=jain.numpy(),
                          terminated=np.zeros(b, dtype=bool), truncated=np.full(b, done))

    def place(self, pos, bw_logit) -> StepOutput:
        """Move to slot t+1 with the fleet PLACED at ``pos`` (B, K, 2) metres, every UAV active, and serve x_{t+1}
        with ``bw_logit`` (B, K), exactly as :meth:`step` serves a flown fleet: the per-slot bound's step
        (``dswm.methods.ceiling``), with no motion limit, no battery and no flight, hence no energy and no reward
        (NaN). Positions are clipped to the area and logits to [-1, 1], the controllers' range; NaN/inf or a wrong
        shape raise ValueError."""
        if self.t >= self.scenario.slots_per_day - 1:
            raise RuntimeError("place() after the end of the day: call reset() first")
        b, k = len(self.days), self.scenario.n_uavs
        p = torch.as_tensor(np.asarray(pos, dtype=np.float32), device=self.device)
        lg = torch.as_tensor(np.asarray(bw_logit, dtype=np.float32), device=self.device)
        for name, value, shape in (("pos", p, (b, k, 2)), ("bw_logit", lg, (b, k))):
            if tuple(value.shape) != shape:
                raise ValueError(f"placement {name}: expected shape {shape}, found {tuple(value.shape)}")
            if not torch.isfinite(value).all():
                where = torch.nonzero(~torch.isfinite(value))[0].tolist()
                raise ValueError(f"placement {name}: non-finite value at episode {where[0]}, UAV {where[1]}")
        with torch.no_grad():
            self.state = FleetState(pos=self.geom.clip(p), battery_j=self.state.battery_j,
                                    status=torch.full((b, k), ACTIVE, dtype=torch.long, device=self.device),
                                    charge_left=torch.zeros((b, k), dtype=torch.long, device=self.device))
            self.t += 1
            x = self.demand[self.days, self.t]
            res = self._serve(x, self.state, lg.clamp(-1.0, 1.0))
            jain = jain_index(res.fulfilment, x, self.scenario.u_peak)
            self._served = (x, res)
        nan = np.full(b, np.nan)
        return StepOutput(obs=self.observe(), reward=nan, sr=res.sr.numpy(), energy_j=nan.copy(), jain=jain.numpy(),
                          terminated=np.zeros(b, dtype=bool),
                          truncated=np.full(b, self.t >= self.scenario.slots_per_day - 1))


def grid_of(tensor) -> Grid:
    """The Grid of a prepared tensor (``prep.tensor.DemandTensor``)."""
    return Grid(rows=tensor.grid.rows, cols=tensor.grid.cols, cell_m=tensor.grid.cell_m)


def initial_deployment(tensor, grid: Grid, scenario: Scenario) -> np.ndarray:
    """(K, 2) demand-weighted K-means of the mean TRAINING map of ``tensor`` (the same for every method)."""
    train_mean = tensor.demand[tensor.train_days].mean(axis=(0, 1))
    return initial_positions(train_mean, grid, scenario.n_uavs, scenario.init.kmeans_seed)


def core_from_tensor(tensor, scenario: Scenario, days, *, device: str = "cpu") -> FleetCore:
    """The one way from a prepared tensor to the environment: a FleetCore over tensor days ``days``.

    Its grid is the tensor's, its initial deployment :func:`initial_deployment`, its day labels the tensor's
    own (``tensor.labels``); ``core.day_ids`` maps each of its days back to the tensor day index.
    """
    days = np.asarray(days, dtype=np.int64)
    grid = grid_of(tensor)
    labels = tensor.labels
    core = FleetCore(demand=np.ascontiguousarray(tensor.demand[days]), grid=grid, scenario=scenario,
                     init_pos=initial_deployment(tensor, grid, scenario), dataset=tensor.meta["dataset"],
                     day_labels=[labels[d] for d in days], device=device)
    core.day_ids = days
    return core
