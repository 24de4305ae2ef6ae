"""``DSWMController``: the controller of the methods ``dswm``, ``dswm_wo_unc`` and ``dswm_wo_dec``.

The three methods are configurations of the same code (config.yaml ``dswm.methods``): ``dswm_wo_unc`` sets
lambda_u = 0, ``dswm_wo_dec`` replaces the decomposed physics head by an SR-MLP on the latent state. The
profile (``profile:`` of the resolved config) selects ``dswm.budgets.<profile>``: collected transitions,
gradient steps and any planner-size reductions.

Per slot (Algorithm 1): filter o_t into the posterior, then CEM over H-slot sequences scored by
``ImaginationScorer`` (anchored imagined demand, fleet propagated by ``dswm.fleet``, service head), and
execute the first action of the best sequence; the CEM mean is carried to the next slot (warm start). With
``planner.proposal: bcd`` the population is seeded with a block-coordinate-descent move (the greedy
baseline's search, as strong as the oracle's) on the ANCHORED IMAGINED next-slot map, i.e. on what the world
model expects, never on the true next map; ``dswm_wo_dec`` has no proposal (it has no service physics).
"""
from __future__ import annotations

import copy
import dataclasses
import hashlib
import time
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import torch

from dswm.atomic import atomic_path
from dswm.config import stable_hash
from dswm.controllers import Controller, DayContext
from dswm.core import Grid, fleet_state_from_obs
from dswm.physics import ServiceParams
from dswm.planner import PROPOSALS, AnchoredCEMPlanner, ImaginationScorer, PlannerConfig, anchor
from dswm.rssm import RSSMConfig
from dswm.training import TrainConfig, collect, save_training_figure, train
from dswm.world_model import WorldModel, WorldModelConfig

METHODS = ("dswm", "dswm_wo_unc", "dswm_wo_dec")
_RSSM_KEYS = {f.name for f in dataclasses.fields(RSSMConfig)} - {"action_dim"}


def _merge(base: Mapping[str, Any], over: Mapping[str, Any] | None) -> dict:
    out = copy.deepcopy(dict(base))
    for k, v in (over or {}).items():
        out[k] = _merge(out[k], v) if isinstance(v, Mapping) and isinstance(out.get(k), Mapping) else v
    return out


def _build(cls, data: Mapping[str, Any], where: str, **fixed):
    """Dataclass ``cls`` from a config mapping; unknown or missing keys raise naming the config key."""
    names = {f.name for f in dataclasses.fields(cls)} - set(fixed)
    unknown, missing = sorted(set(data) - names), sorted(names - set(data))
    if unknown or missing:
        raise ValueError(f"config.yaml: key '{where}': unknown keys {unknown}, missing keys {missing} "
                         f"(expected exactly {sorted(names)})")
    return cls(**dict(data), **fixed)


@dataclasses.dataclass(frozen=True)
class DSWMSettings:
    """Resolved settings of one method under one profile."""

    world_model: dict
    training: TrainConfig
    planner: PlannerConfig
    transitions: int
    steps: int
    device: str

    def wm_config(self, n_uavs: int) -> WorldModelConfig:
        wm = dict(self.world_model)
        rssm = RSSMConfig(action_dim=3 * n_uavs, **{k: wm.pop(k) for k in _RSSM_KEYS})
        return _build(WorldModelConfig, wm, "dswm.world_model", rssm=rssm)


def settings(dswm_cfg: Mapping[str, Any], *, method: str, profile: str) -> DSWMSettings:
    """Resolve config.yaml's ``dswm`` section for ``method`` under ``profile``.

    Method overrides (``dswm.methods.<method>``) and the profile's planner reductions
    (``dswm.budgets.<profile>.planner``) are merged over the base sections.
    """
    if method not in METHODS:
        raise ValueError(f"DSWMController: method must be one of {METHODS}, found {method!r}")
    budgets = dswm_cfg["budgets"]
    if profile not in budgets:
        raise ValueError(f"config.yaml: key 'dswm.budgets' has no entry {profile!r} (found {sorted(budgets)})")
    over = dswm_cfg["methods"].get(method) or {}
    budget = budgets[profile]
    wm = _merge(dswm_cfg["world_model"], over.get("world_model"))
    planner = _merge(_merge(dswm_cfg["planner"], budget.get("planner")), over.get("planner"))
    planner["proposal_bw_logits"] = tuple(float(v) for v in planner.get("proposal_bw_logits", ()))
    if planner.get("proposal") not in PROPOSALS:
        raise ValueError(f"config.yaml: key 'dswm.planner.proposal' must be one of {PROPOSALS}, "
                         f"found {planner.get('proposal')!r}")
    planner_cfg = _build(PlannerConfig, planner, "dswm.planner")
    # The one cross-key check the schema cannot make: it sees each section, not the merged planner.
    if not 1 <= planner_cfg.n_elites <= planner_cfg.n_samples:
        raise ValueError(f"config.yaml: key 'dswm.planner.n_elites' must lie in [1, n_samples] (after the "
                         f"'dswm.budgets.{profile}.planner' and 'dswm.methods.{method}.planner' overrides); found "
                         f"n_elites={planner_cfg.n_elites}, n_samples={planner_cfg.n_samples}")
    return DSWMSettings(world_model=wm,
                        training=_build(TrainConfig, _merge(dswm_cfg["training"], over.get("training")),
                                        "dswm.training"),
                        planner=planner_cfg,
                        transitions=int(budget["transitions"]), steps=int(budget["steps"]),
                        device=str(dswm_cfg["device"]))


def training_hash(s: DSWMSettings, budget: Mapping[str, Any]) -> str:
    """Hash of everything that shapes training: world model, training section and budget (not the planner)."""
    return stable_hash({"world_model": s.world_model, "training": dataclasses.asdict(s.training),
                        "budget": dict(budget)})


def training_inputs_hash(core, day_ids: np.ndarray) -> str:
    """Hash of what a training run reads besides its settings: the training-day demand tensor, its day ids
    (tensor day of each of ``core``'s days) and labels, the grid and the scenario of ``core`` (a FleetCore of
    TRAINING days)."""
    demand = hashlib.sha256(np.ascontiguousarray(core.demand.detach().cpu().numpy()).tobytes()).hexdigest()
    return stable_hash({"demand_sha256": demand, "day_ids": day_ids.tolist(), "day_labels": list(core.day_labels),
                        "grid": dataclasses.asdict(core.grid), "scenario": dataclasses.asdict(core.scenario)})


class BCDProposal:
    """The "bcd" proposal: the greedy baseline's block-coordinate descent (``dswm.baselines``), pointed at the
    anchored imagined next-slot map instead of the observed one, with the bandwidth logits searched too."""

    def __init__(self, *, sweeps: int, lattice: int, refine: int, bw_logits: tuple):
        from dswm.baselines import GreedyController

        class _AnchoredBCD(GreedyController):
            def target_demand(self, obs):
                return self.target

        self.bcd = _AnchoredBCD(name="dswm-proposal", sweeps=sweeps, lattice=lattice, refine=refine)
        self.bcd.bw_logits = tuple(sorted(bw_logits, key=abs))   # 0 first: ties keep the proportional split

    def reset(self, ctx: DayContext) -> None:
        self.bcd.reset_batch([ctx])

    def __call__(self, obs: Mapping[str, Any], target: torch.Tensor) -> torch.Tensor:
        """(K, 3) move for one observation, scored on ``target`` (G,)."""
        self.bcd.target = target.reshape(1, -1).float().cpu()
        return torch.as_tensor(self.bcd.act_batch({k: np.asarray(v)[None] for k, v in obs.items()})[0])


class DSWMController(Controller):
    """Decision-time planner over a learned world model (see module docstring)."""

    learns = True

    def __init__(self, *, name: str, seed: int = 0, device: str = "cpu", settings: DSWMSettings):
        super().__init__(name=name, seed=seed, device=device)
        self.settings = settings
        self.model: WorldModel | None = None
        self.plan_ms: list[float] = []

    @classmethod
    def from_config(cls, *, name: str, config: Mapping[str, Any], seed: int) -> "DSWMController":
        s = settings(config["dswm"], method=name, profile=config["profile"])
        return cls(name=name, seed=seed, device=s.device, settings=s)

    @classmethod
    def budget_from_config(cls, *, name: str, config: Mapping[str, Any]) -> dict:
        s = settings(config["dswm"], method=name, profile=config["profile"])
        return {"transitions": s.transitions, "steps": s.steps}

    @classmethod
    def training_identity(cls, *, name: str, config: Mapping[str, Any]) -> str:
        """:func:`training_hash` of the method under the selected profile: ``dswm_wo_unc`` (a planner override
        only) trains what ``dswm`` trains; ``dswm_wo_dec`` (a world-model override) does not."""
        s = settings(config["dswm"], method=name, profile=config["profile"])
        return training_hash(s, cls.budget_from_config(name=name, config=config))

    def settings_hash(self, budget: Mapping[str, Any]) -> str:
        """:func:`training_hash` of this controller (a checkpoint resumes only under the same hash)."""
        return training_hash(self.settings, budget)

    # ---- model construction ---------------------------------------------------------------------------
    def _build_model(self, grid: Grid, scenario) -> WorldModel:
        self.grid, self.scenario = grid, scenario
        self.params = ServiceParams.from_scenario(scenario)
        model = WorldModel(cfg=self.settings.wm_config(scenario.n_uavs), rows=grid.rows, cols=grid.cols,
                           n_uavs=scenario.n_uavs, window=scenario.obs_window + 1,
                           cells=grid.cells(), params=self.params)
        return model.to(self.device)

    def fit(self, train_core, *, budget: Mapping[str, Any], run_dir) -> dict:
        """Pre-collect on the TRAINING-days core, train the world model, checkpoint; return the manifest."""
        run_dir = Path(run_dir)
        run_dir.mkdir(parents=True, exist_ok=True)
        day_ids = np.asarray(getattr(train_core, "day_ids", range(train_core.n_days)), dtype=np.int64)
        torch.manual_seed(self.seed)
        replay = collect(train_core, n_transitions=int(budget["transitions"]), cfg=self.settings.training,
                         seed=self.seed, day_ids=day_ids)
        self.model = self._build_model(train_core.grid, train_core.scenario)
        self.model.set_normalizer(replay.demand)
        ckpt = run_dir / "checkpoint.pt"
        # A checkpoint resumes only the same run: same settings AND the same training data, scenario and days
        # (a rerun after the tensor or the scenario changed trains from scratch).
        history = train(self.model, replay, steps=int(budget["steps"]), cfg=self.settings.training,
                        seed=self.seed, checkpoint=ckpt, resume=True,
                        extra={"method": self.name, "seed": self.seed, "settings": self.settings_hash(budget),
                               "inputs": training_inputs_hash(train_core, day_ids)})
        save_training_figure(history, run_dir / "training_diagnostics.png")
        return {"days": replay.episode_days(), "day_labels": [train_core.day_labels[r] for r in replay.rows],
                "transitions_per_day_episode": train_core.scenario.slots_per_day - 1,
                "n_transitions": replay.n_transitions, "steps": int(budget["steps"]),
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
        if blob.get("method") not in METHODS:
            raise ValueError(f"{path}: not a DSWM model file (method {blob.get('method')!r})")
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
        self.ctx, self.geom = ctx, ctx.geometry
        self.cells = torch.as_tensor(ctx.cells, dtype=torch.float32, device=self.device)
        k = self.scenario.n_uavs
        self.latent = self.model.rssm.initial(1, device=self.device)
        self.last_action = torch.zeros(1, k, 3, device=self.device)
        cfg = self.settings.planner
        self.planner = AnchoredCEMPlanner(cfg=cfg, n_uavs=k, device=self.device, seed=self.seed)
        self.planner.reset(ctx.day)
        self.proposal = None
        if cfg.proposal == "bcd":
            self.proposal = BCDProposal(sweeps=cfg.proposal_sweeps, lattice=cfg.proposal_lattice,
                                        refine=cfg.proposal_refine, bw_logits=cfg.proposal_bw_logits)
            self.proposal.reset(ctx)

    def _proposals(self, obs: Mapping[str, Any], x_now: torch.Tensor) -> torch.Tensor | None:
        """(M, H, K, 3) seed sequences: the BCD move on the anchored imagined next map, then hold / then the
        previous plan's continuation."""
        if self.proposal is None:
            return None
        cfg, planner = self.settings.planner, self.planner
        mean0 = planner.warm_mean()[0]
        prior = self.model.rssm.img_step(self.latent, mean0.reshape(1, -1), sample=False)
        x_next, _ = anchor(x_now, self.model.demand_members(self.model.rssm.feat(prior)), cfg.rho)
        first = self.proposal(obs, x_next[0]).to(self.device)
        hold = torch.zeros(cfg.horizon, self.scenario.n_uavs, 3, device=self.device)
        seqs = [hold.clone(), planner.warm_best() if planner.warm_best() is not None else hold.clone()]
        for q in seqs:
            q[0] = first
        return torch.stack(seqs)

    def act(self, obs: Mapping[str, Any]) -> np.ndarray:
        t0 = time.perf_counter()
        dev, cfg = self.device, self.settings.planner
        demand = torch.as_tensor(np.asarray(obs["demand"]), dtype=torch.float32, device=dev)
        fleet_obs = torch.as_tensor(np.asarray(obs["fleet"]), dtype=torch.float32, device=dev)
        time_obs = torch.as_tensor(np.asarray(obs["time"]), dtype=torch.float32, device=dev)
        with torch.inference_mode():
            self.latent = self.model.filter_step(self.latent, self.last_action, demand[None], fleet_obs[None],
                                                 time_obs[None])
            fleet = fleet_state_from_obs(obs["fleet"], self.grid, self.scenario)
            fleet = type(fleet)(*(t.to(dev) for t in fleet))
            scorer = ImaginationScorer(model=self.model, latent=self.latent, fleet=fleet,
                                       x_now=demand[-1].reshape(-1), geom=self.geom, scenario=self.scenario,
                                       params=self.params, cells=self.cells, gamma=cfg.gamma, rho=cfg.rho,
                                       lambda_u=cfg.lambda_u, continuation=cfg.continuation,
                                       compile=cfg.compile)
            action, _ = self.planner.plan(scorer, self._proposals(obs, demand[-1].reshape(-1)))
        self.last_action = action.unsqueeze(0)
        self.plan_ms.append(1000.0 * (time.perf_counter() - t0))
        return action.cpu().numpy().astype(np.float32)
