"""The controllers of the CEM planner over an imagined fleet (config.yaml ``dswm``).

* ``DSWMController``: ``dswm`` (the paper's Algorithm 1), its ablations ``dswm_wo_unc`` (lambda_u = 0) and
  ``dswm_wo_dec`` (SR-MLP head), and ``dswm_plus`` (the project's planner). Per slot: filter o_t into the
  posterior, then CEM over H-slot sequences scored by ``ImaginationScorer`` (anchored imagined demand, fleet
  propagated by ``dswm.sim.fleet``, service head), and execute the first action of the best sequence.
* ``PersistenceController`` (``dswm_plus_persist``): the same planner with the model's demand replaced by the
  current map held constant over the horizon (no model, no uncertainty). It probes what the world model adds.
* ``PerfectForecastController`` (``perfect``): the same planner fed the TRUE maps x_{t+1..t+H} (clairvoyant).

All are configurations of one code path (``dswm.methods.dswm.settings.resolve``); the profile selects
``dswm.budgets.<profile>`` (collected transitions, gradient steps and planner-size reductions). With
``planner.proposal: bcd`` the population is seeded with the project's one BCD search (config.yaml ``search``) on
the first imagined map: the model's anchored next map, the current map (persistence) or the true next map
(perfect forecast).
"""
from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Any, ClassVar, Mapping

import numpy as np
import torch

from dswm.config import stable_hash, to_plain
from dswm.methods.base import Controller, DayContext, training_inputs_hash
from dswm.methods.collect import collect
from dswm.methods.dswm.planner import AnchoredCEMPlanner, ImaginationScorer, ImaginedWorld, StepScoring, anchor
from dswm.methods.dswm.settings import DSWMSettings, resolve
from dswm.methods.dswm.training import save_training_figure, train
from dswm.methods.dswm.world_model import WorldModel
from dswm.methods.search import SearchSettings, bcd_search, configured_search, to_action
from dswm.sim.core import Grid, fleet_state_from_obs
from dswm.sim.physics import ServiceParams
from prep.atomic import atomic_path



class BCDProposal:
    """The "bcd" proposal: the project's block-coordinate-descent search (``dswm.methods.search``) on a map the
    planner imagines for the next slot, with the shared search settings."""

    def __init__(self, search: SearchSettings):
        self.search = search

    def reset(self, ctx: DayContext) -> None:
        self.grid, self.scenario, self.geom = ctx.grid, ctx.scenario, ctx.geometry
        self.cells = torch.as_tensor(ctx.cells, dtype=torch.float32)
        self.params = ServiceParams.from_scenario(ctx.scenario)

    def __call__(self, obs: Mapping[str, Any], target: torch.Tensor) -> torch.Tensor:
        """(K, 3) move for one observation, scored on ``target`` (G,)."""
        state = fleet_state_from_obs(np.asarray(obs["fleet"])[None], self.grid, self.scenario)
        with torch.no_grad():
            plan, logit = bcd_search(state, target.reshape(1, -1).float().cpu(), search=self.search,
                                     cells=self.cells, geom=self.geom, scenario=self.scenario, params=self.params)
        move = to_action(plan, state.pos, self.scenario.d_max_m)
        return torch.cat([move, logit.unsqueeze(-1)], dim=-1)[0]


class PlanningController(Controller):
    """CEM over H-slot sequences of an imagined fleet; a subclass says what demand the imagination scores on
    (:meth:`_scorer`). Settings: ``DSWMSettings`` (its ``planner`` acts here)."""

    options_type: ClassVar[type] = DSWMSettings

    def __init__(self, *, name: str, seed: int = 0, device: str = "cpu", options: DSWMSettings):
        super().__init__(name=name, seed=seed, device=options.device, options=options)
        self.plan_ms: list[float] = []

    @property
    def settings(self) -> DSWMSettings:
        """The method's typed settings (its ``options``)."""
        return self.options

    @classmethod
    def options_from_config(cls, *, name: str, config: Mapping[str, Any], profile: str) -> DSWMSettings:
        """config.yaml's ``dswm`` section merged for ``name`` and ``profile``, with the shared ``search`` under the
        same profile (``dswm.methods.dswm.settings``)."""
        return resolve(config["dswm"], method=name, profile=profile, search=configured_search(config, profile)[0])

    def search_settings(self) -> SearchSettings | None:
        """The shared BCD search when the planner is seeded by the "bcd" proposal, else None."""
        cfg = self.settings.planner
        return cfg.search if cfg is not None and cfg.proposal == "bcd" else None

    def _start_day(self, ctx: DayContext, grid: Grid, scenario) -> None:
        """The planner, proposal and geometry of one day (after the subclass's checks)."""
        if self.settings.planner is None:
            raise RuntimeError(f"{self.name}: built with training settings only (no planner); it cannot act")
        self.grid, self.scenario = grid, scenario
        self.params = ServiceParams.from_scenario(scenario)
        self.ctx, self.geom = ctx, ctx.geometry
        self.cells = torch.as_tensor(ctx.cells, dtype=torch.float32, device=self.device)
        cfg = self.settings.planner
        self.planner = AnchoredCEMPlanner(cfg=cfg, n_uavs=scenario.n_uavs, device=self.device, seed=self.seed)
        self.planner.reset(ctx.day)
        self.proposal = None
        if cfg.proposal == "bcd":
            self.proposal = BCDProposal(cfg.search)
            self.proposal.reset(ctx)

    def _scorer(self, obs: Mapping[str, Any], demand: torch.Tensor, fleet) -> tuple[ImaginationScorer, torch.Tensor | None]:
        """The scorer of this slot and the first imagined map (G,) the proposal searches on (None: no proposal).

        Args:
            obs: the observation; demand: (w+1, R, C) its maps on the device; fleet: its FleetState (K, ...).
        """
        raise NotImplementedError

    def _proposals(self, obs: Mapping[str, Any], first_map: torch.Tensor | None) -> torch.Tensor | None:
        """(M, H, K, 3) seed sequences: the BCD move on the first imagined map, then hold / then the previous
        plan's continuation."""
        if self.proposal is None:
            return None
        cfg, planner = self.settings.planner, self.planner
        first = self.proposal(obs, first_map).to(self.device)
        hold = torch.zeros(cfg.horizon, self.scenario.n_uavs, 3, device=self.device)
        seqs = [hold.clone(), planner.warm_best() if planner.warm_best() is not None else hold.clone()]
        for q in seqs:
            q[0] = first
        return torch.stack(seqs)

    def act(self, obs: Mapping[str, Any]) -> np.ndarray:
        t0 = time.perf_counter()
        demand = torch.as_tensor(np.asarray(obs["demand"]), dtype=torch.float32, device=self.device)
        with torch.inference_mode():
            fleet = fleet_state_from_obs(obs["fleet"], self.grid, self.scenario)
            fleet = type(fleet)(*(t.to(self.device) for t in fleet))
            scorer, first_map = self._scorer(obs, demand, fleet)
            if first_map is not None and self.settings.planner.imagine_scale != 1.0:
                first_map = self.settings.planner.imagine_scale * first_map   # the do(s) probe: s x imagined map
            action, _ = self.planner.plan(scorer, self._proposals(obs, first_map))
        self._acted(action)
        self.plan_ms.append(1000.0 * (time.perf_counter() - t0))
        return action.cpu().numpy().astype(np.float32)

    def _acted(self, action: torch.Tensor) -> None:
        """Hook: the action (K, 3) just chosen."""

    def _imagination(self, demand: torch.Tensor, fleet, *, model=None, latent=None,
                     maps: torch.Tensor | None = None) -> ImaginationScorer:
        """The planner's scorer of this slot: on the world model's anchored ensemble (``model``, ``latent``) or
        on given maps (H, G) instead (``maps``)."""
        cfg = self.settings.planner
        world = ImaginedWorld(cells=self.cells, geom=self.geom, scenario=self.scenario, params=self.params)
        scoring = StepScoring(rho=cfg.rho, lambda_u=cfg.lambda_u, continuation=cfg.continuation,
                              scale=cfg.imagine_scale, rho_steps=cfg.rho_steps)
        return ImaginationScorer(model=model, latent=latent, fleet=fleet, x_now=demand[-1].reshape(-1), world=world,
                                 scoring=scoring, gamma=cfg.gamma, compile=cfg.compile, demand_override=maps)


class PersistenceController(PlanningController):
    """DSWM+'s planner on the current map held constant over the horizon (the probe ``dswm_plus_persist``)."""

    def save(self, path) -> None:
        """Nothing to save: no learned state."""

    def load(self, path) -> None:
        """Nothing to load."""

    def reset(self, ctx: DayContext) -> None:
        self._start_day(ctx, ctx.grid, ctx.scenario)

    def _scorer(self, obs, demand, fleet):
        x_now = demand[-1].reshape(-1)
        maps = x_now.expand(self.settings.planner.horizon, -1)
        return self._imagination(demand, fleet, maps=maps), x_now


class PerfectForecastController(PersistenceController):
    """DSWM+'s planner fed the TRUE maps x_{t+1..t+H} (``perfect``): what any forecast could add, at most.
    Past the day's last slot the last map stands in (those steps follow the day's end)."""

    clairvoyant = True

    def reset(self, ctx: DayContext) -> None:
        if ctx.demand is None:
            raise ValueError(f"{self.name}: the day context of {ctx.label} carries no true demand; the method is "
                             f"clairvoyant and must be given it")
        super().reset(ctx)
        true = torch.as_tensor(np.asarray(ctx.demand, dtype=np.float32), device=self.device)
        self.future = true.reshape(true.shape[0], -1)  # (T, G)
        self.t = 0

    def _scorer(self, obs, demand, fleet):
        horizon, last = self.settings.planner.horizon, self.future.shape[0] - 1
        idx = torch.clamp(torch.arange(self.t + 1, self.t + 1 + horizon, device=self.device), max=last)
        self.t += 1
        maps = self.future[idx]
        return self._imagination(demand, fleet, maps=maps), maps[0]


class DSWMController(PlanningController):
    """Decision-time planner over a learned world model (see module docstring)."""

    learns = True
    shares_training = True

    def __init__(self, *, name: str, seed: int = 0, device: str = "cpu", options: DSWMSettings):
        super().__init__(name=name, seed=seed, device=device, options=options)
        self.model: WorldModel | None = None

    @classmethod
    def training_settings(cls, options: DSWMSettings) -> DSWMSettings:
        """Everything but the planner: methods that differ in their planner only (``dswm_wo_unc``, ``dswm_plus``)
        train what ``dswm`` trains; ``dswm_wo_dec`` (a world-model override) does not."""
        return dataclasses.replace(options, planner=None)

    def settings_hash(self) -> str:
        """Hash of this controller's training settings (a checkpoint resumes only under the same hash)."""
        return stable_hash(to_plain(self.training_settings(self.settings)))

    # ---- model construction ---------------------------------------------------------------------------
    def _build_model(self, grid: Grid, scenario) -> WorldModel:
        self.grid, self.scenario = grid, scenario
        self.params = ServiceParams.from_scenario(scenario)
        model = WorldModel(cfg=self.settings.world_model, rows=grid.rows, cols=grid.cols,
                           n_uavs=scenario.n_uavs, window=scenario.obs_window + 1,
                           cells=grid.cells(), params=self.params)
        return model.to(self.device)

    def fit(self, train_core, *, run_dir, snapshots=None) -> dict:
        """Pre-collect on the TRAINING-days core, train the world model, checkpoint; return the manifest.
        ``snapshots``: see ``Controller.fit`` (the budget is the gradient steps; every snapshot has consumed the
        pre-collected transitions, all collected before the first step)."""
        run_dir = Path(run_dir)
        run_dir.mkdir(parents=True, exist_ok=True)
        day_ids = np.asarray(getattr(train_core, "day_ids", range(train_core.n_days)), dtype=np.int64)
        torch.manual_seed(self.seed)
        replay = collect(train_core, n_transitions=self.settings.transitions, cfg=self.settings.training,
                         seed=self.seed, day_ids=day_ids)
        self.model = self._build_model(train_core.grid, train_core.scenario)
        self.model.set_normalizer(replay.demand)
        ckpt = run_dir / "checkpoint.pt"

        def take_snapshot(done: int) -> None:
            snapshots.step(done=done, total=self.settings.steps, n_transitions=replay.n_transitions,
                           gradient_steps=done, write=self.save)

        if snapshots is not None:
            snapshots.claim(ckpt)
            snapshots.start(total=self.settings.steps, n_transitions=replay.n_transitions, write=self.save)
        # A checkpoint resumes only the same run: same settings AND the same training data, scenario and days
        # (a rerun after the tensor or the scenario changed trains from scratch).
        history = train(self.model, replay, steps=self.settings.steps, cfg=self.settings.training,
                        seed=self.seed, checkpoint=ckpt, resume=True,
                        extra={"method": self.name, "seed": self.seed, "settings": self.settings_hash(),
                               "inputs": training_inputs_hash(train_core, day_ids)},
                        on_step=take_snapshot if snapshots is not None else None)
        save_training_figure(history, run_dir / "training_diagnostics.png")
        return {"days": replay.episode_days(), "day_labels": [train_core.day_labels[r] for r in replay.rows],
                "transitions_per_day_episode": train_core.scenario.slots_per_day - 1,
                "n_transitions": replay.n_transitions, "steps": self.settings.steps,
                "checkpoint": str(ckpt),
                "checkpoint_written_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(ckpt.stat().st_mtime)),
                "read_test_data": False, "history": history}

    def save(self, path) -> None:
        """Weights (teacher and normalizer buffers included), grid and scenario needed to rebuild the model."""
        if self.model is None:
            raise RuntimeError(f"{self.name}: nothing to save, the model is not trained")
        blob = {"model": self.model.state_dict(), "grid": dataclasses.asdict(self.grid),
                "scenario": self.scenario, "method": self.name, "seed": self.seed,
                "torch_rng": torch.get_rng_state()}
        with atomic_path(path) as tmp:
            torch.save(blob, tmp)

    def load(self, path) -> None:
        blob = torch.load(path, map_location=self.device, weights_only=False)
        if not isinstance(blob, dict) or any(k not in blob for k in ("model", "grid", "scenario")):
            raise ValueError(f"{path}: not a DSWM model file (expected the keys model, grid, scenario)")
        self.model = self._build_model(Grid(**blob["grid"]), blob["scenario"])
        self.model.load_state_dict(blob["model"])
        self.model.eval()

    # ---- acting ----------------------------------------------------------------------------------------
    def reset(self, ctx: DayContext) -> None:
        if self.model is None:
            raise RuntimeError(f"{self.name}: reset() before fit() or load()")
        g = ctx.grid
        if (g.rows, g.cols) != (self.model.rows, self.model.cols):
            raise ValueError(f"{self.name}: model trained on a {self.model.rows}x{self.model.cols} grid, "
                             f"day {ctx.label} of {ctx.dataset} has {g.rows}x{g.cols}")
        if ctx.scenario.hash() != self.scenario.hash():
            raise ValueError(f"{self.name}: model trained under scenario hash {self.scenario.hash()}, day "
                             f"{ctx.label} of {ctx.dataset} is evaluated under {ctx.scenario.hash()}; retrain it")
        self._start_day(ctx, self.grid, self.scenario)
        self.latent = self.model.rssm.initial(1, device=self.device)
        self.last_action = torch.zeros(1, self.scenario.n_uavs, 3, device=self.device)

    def _scorer(self, obs, demand, fleet):
        """Filter o_t into the posterior; score on the model's anchored ensemble. The first imagined map is the
        anchored prior mean after the warm-start mean's first action (only computed for a proposal)."""
        cfg = self.settings.planner
        fleet_obs = torch.as_tensor(np.asarray(obs["fleet"]), dtype=torch.float32, device=self.device)
        time_obs = torch.as_tensor(np.asarray(obs["time"]), dtype=torch.float32, device=self.device)
        self.latent = self.model.filter_step(self.latent, self.last_action, demand[None], fleet_obs[None],
                                             time_obs[None])
        x_now = demand[-1].reshape(-1)
        scorer = self._imagination(demand, fleet, model=self.model, latent=self.latent)
        first_map = None
        if self.proposal is not None:
            mean0 = self.planner.warm_mean()[0]
            prior = self.model.rssm.img_step(self.latent, mean0.reshape(1, -1), sample=False)
            x_next, _ = anchor(x_now, self.model.demand_members(self.model.rssm.feat(prior)), cfg.rho_at(1))
            first_map = x_next[0]
        return scorer, first_map

    def _acted(self, action: torch.Tensor) -> None:
        self.last_action = action.unsqueeze(0)
