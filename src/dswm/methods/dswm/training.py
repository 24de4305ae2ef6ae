"""Offline training of the DSWM world model (paper Algorithm 2).

1. Heuristic pre-collection on the TRAINING-days core only (every episode records its tensor day index).
2. Gradient steps on replayed sequences with the loss of eq. 15 plus the ensemble calibration term
   (``WorldModel.loss``), Adam at the configured learning rate, EMA teacher update after every step.
3. Complete checkpoints (weights incl. teacher and normalizer buffers, optimizer, RNG states, step, history),
   written atomically; ``train`` resumes from one and reproduces the very next losses.
The loss history is returned as arrays ({"losses/<term>": [...], "step": [...]}) for MLflow batch logging and
drawn by ``save_training_figure`` as the training-diagnostics figure.
"""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Callable

import numpy as np
import torch
from tqdm import tqdm

from prep.atomic import atomic_path
from dswm.sim.core import fleet_state_from_obs
from dswm.sim.fleet import available
from dswm.sim.physics import associate
from dswm.methods.dswm.planner import lloyd_step
from dswm.methods.dswm.replay import SequenceReplay
from dswm.methods.dswm.world_model import WorldModel

COLLECT_POLICIES = ("lloyd", "greedy")
HISTORY_KEYS = ("loss", "dem", "cal", "kl", "kl_dyn", "kl_rep", "lpr_pred", "lpr_var", "serve", "h_std")


@dataclasses.dataclass(frozen=True, kw_only=True)
class TrainConfig:
    """Optimization and pre-collection settings (values and reasons in config.yaml ``dswm.training``)."""

    lr: float
    batch: int
    """Sequences per gradient step."""
    seq_len: int
    """Decisions per replayed sequence."""
    grad_clip: float
    """Global gradient-norm clip."""
    collect_policy: str
    """"lloyd" (move to the demand centroid of the UAV's Voronoi region) or "greedy" (dswm.methods.classical)."""
    collect_parallel: int
    """Training days stepped together during pre-collection."""
    explore_std: float
    """Std of the Gaussian noise added to the heuristic's moves (fraction of D_max)."""
    bw_explore_std: float
    """Std of the Gaussian bandwidth logits of the pre-collection policy."""
    log_points: int
    """Number of points of the loss history (averages over equal windows of steps)."""
    checkpoint_every: int
    """Gradient steps between checkpoints (the last step always writes one)."""


# ---- pre-collection -------------------------------------------------------------------------------------
def lloyd_moves(obs: dict, core, rng: np.random.Generator, cfg: TrainConfig) -> np.ndarray:
    """Heuristic action (B, K, 3): each UAV heads for the demand-weighted centroid of the cells it serves
    (``dswm.methods.dswm.planner.lloyd_step``), plus exploration noise; bandwidth logits are drawn around 0."""
    state = fleet_state_from_obs(obs["fleet"], core.grid, core.scenario)
    x = torch.as_tensor(obs["demand"][:, -1]).reshape(len(state.pos), -1)     # (B, G)
    cells = core.cells.cpu().float()
    assoc = associate(state.pos, available(state), cells)                    # (B, G)
    move = lloyd_step(x, assoc, state.pos, cells, core.scenario.d_max_m)
    b, k = state.status.shape
    noise = rng.normal(0.0, cfg.explore_std, size=(b, k, 2))
    bw = rng.normal(0.0, cfg.bw_explore_std, size=(b, k, 1))
    return np.clip(np.concatenate([move.numpy() + noise, bw], -1), -1.0, 1.0).astype(np.float32)


def _greedy_policy(core):
    """A batched greedy controller over the core's days (lazy import: baselines are optional here)."""
    from dswm.methods.base import DayContext
    from dswm.methods.classical import GreedyController
    from dswm.methods.search import SearchSettings

    # A cheap search (one sweep, 5x5 lattice, proportional split): pre-collection needs varied, sensible moves.
    greedy = GreedyController(name="greedy", options=SearchSettings(sweeps=1, lattice=5, refine=0, bw_logits=()))

    def reset(rows):
        greedy.reset_batch([DayContext(dataset=core.dataset, day=int(r), label=core.day_labels[r], split="train",
                                       grid=core.grid, scenario=core.scenario, geometry=core.geom, cells=core.cells,
                                       init_pos=core.init_pos.cpu().numpy()) for r in rows])
    return greedy, reset


def collect(core, *, n_transitions: int, cfg: TrainConfig, seed: int, day_ids: np.ndarray) -> SequenceReplay:
    """Play heuristic episodes on the training-days core until ``n_transitions`` decisions are stored.

    Args:
        core: a ``FleetCore`` whose rows are TRAINING days only; day_ids: (D,) their tensor day indices.
        n_transitions: decisions to collect (rounded up to whole days); cfg: settings; seed: noise seed.
    Returns:
        The filled ``SequenceReplay`` (days visited round-robin, ``collect_parallel`` at a time).
    """
    if cfg.collect_policy not in COLLECT_POLICIES:
        raise ValueError(f"dswm.training.collect_policy: expected one of {COLLECT_POLICIES}, found "
                         f"{cfg.collect_policy!r}")
    s = core.scenario
    geom = core.geom
    replay = SequenceReplay(demand=core.demand.reshape(core.n_days, s.slots_per_day, core.grid.rows,
                                                       core.grid.cols).cpu().numpy(),
                            day_ids=day_ids, window=s.obs_window, width_m=geom.width_m, height_m=geom.height_m,
                            slots_per_day=s.slots_per_day)
    rng = np.random.default_rng(seed)
    n_dec = s.slots_per_day - 1
    n_episodes = max(1, math.ceil(n_transitions / n_dec))
    greedy = _greedy_policy(core) if cfg.collect_policy == "greedy" else None
    bar = tqdm(total=n_episodes * n_dec, desc="dswm collect", unit="tr", mininterval=5.0)
    done = 0
    while done < n_episodes:
        rows = [(done + j) % core.n_days for j in range(min(cfg.collect_parallel, n_episodes - done))]
        obs = core.reset(rows)
        if greedy is not None:
            greedy[1](rows)
        fleet, acts, srs = [obs["fleet"]], [], []
        for _ in range(n_dec):
            if greedy is None:
                a = lloyd_moves(obs, core, rng, cfg)
            else:
                a = greedy[0].act_batch(obs)
                a[..., :2] += rng.normal(0.0, cfg.explore_std, size=a[..., :2].shape)
                a[..., 2:] = rng.normal(0.0, cfg.bw_explore_std, size=a[..., 2:].shape)
                a = np.clip(a, -1.0, 1.0).astype(np.float32)
            out = core.step(a)
            obs = out.obs
            fleet.append(obs["fleet"])
            acts.append(a)
            srs.append(out.sr)
            bar.update(len(rows))
        fleet, acts, srs = np.stack(fleet, 1), np.stack(acts, 1), np.stack(srs, 1)
        for j, r in enumerate(rows):
            replay.add_episode(row=r, fleet=fleet[j], actions=acts[j], next_sr=srs[j])
        done += len(rows)
    bar.close()
    return replay


# ---- checkpoints ----------------------------------------------------------------------------------------
def save_checkpoint(path: str | Path, *, model: WorldModel, optimizer: torch.optim.Optimizer, step: int,
                    generator: torch.Generator, history: dict, extra: dict) -> None:
    """Write a complete checkpoint atomically (weights, teacher, normalizer buffers, optimizer, RNG, step)."""
    blob = {"model": model.state_dict(), "optimizer": optimizer.state_dict(), "step": step,
            "torch_rng": torch.get_rng_state(), "sample_rng": generator.get_state(),
            "history": history, "extra": extra}
    with atomic_path(path) as tmp:
        torch.save(blob, tmp)


def load_checkpoint(path: str | Path, *, model: WorldModel, optimizer: torch.optim.Optimizer | None = None,
                    generator: torch.Generator | None = None) -> dict:
    """Restore what ``save_checkpoint`` wrote into ``model`` (and optimizer, RNGs); returns the blob."""
    try:
        blob = torch.load(path, map_location=model.cells.device, weights_only=False)
    except FileNotFoundError as err:
        raise FileNotFoundError(f"{path}: DSWM checkpoint not found") from err
    missing = {"model", "step", "torch_rng", "sample_rng"} - set(blob)
    if missing:
        raise ValueError(f"{path}: not a DSWM checkpoint, missing keys {sorted(missing)}")
    model.load_state_dict(blob["model"])
    if optimizer is not None:
        optimizer.load_state_dict(blob["optimizer"])
    if generator is not None:
        generator.set_state(blob["sample_rng"])
        torch.set_rng_state(blob["torch_rng"])
    return blob


# ---- gradient steps -------------------------------------------------------------------------------------
def make_optimizer(model: WorldModel, cfg: TrainConfig) -> torch.optim.Optimizer:
    return torch.optim.Adam(model.online_parameters(), lr=cfg.lr)


def train(model: WorldModel, replay: SequenceReplay, *, steps: int, cfg: TrainConfig, seed: int,
          checkpoint: str | Path, resume: bool = True, extra: dict | None = None,
          on_step: Callable[[int], None] | None = None) -> dict[str, list[float]]:
    """Run gradient steps up to ``steps`` in total (resuming from ``checkpoint`` when it exists).

    Args:
        model: world model (normalizer already set); replay: filled buffer; steps: total gradient steps;
        cfg: settings; seed: seeds torch and the batch sampler; checkpoint: path written every
        ``checkpoint_every`` steps and at the end; resume: continue from ``checkpoint`` if present;
        extra: JSON-able metadata stored with the checkpoint; on_step: called with the steps done after every
        step, before that step's checkpoint (it must leave the model, the optimizer and the RNGs as they are).
    Returns:
        History {"step": [...], "losses/<term>": [...]}: averages over windows of ~steps/log_points steps.
    """
    torch.manual_seed(seed)
    gen = torch.Generator().manual_seed(seed)
    opt = make_optimizer(model, cfg)
    history: dict[str, list[float]] = {"step": [], **{f"losses/{k}": [] for k in HISTORY_KEYS}}
    start = 0
    if resume and Path(checkpoint).exists():
        blob = torch.load(checkpoint, map_location="cpu", weights_only=False)
        if blob.get("extra") == (extra or {}):     # same run (settings hash, method, seed): continue it
            blob = load_checkpoint(checkpoint, model=model, optimizer=opt, generator=gen)
            start, history = int(blob["step"]), blob["history"]
    window = max(1, steps // max(1, cfg.log_points))
    acc = {k: 0.0 for k in HISTORY_KEYS}
    n_acc = 0
    model.train()
    for step in tqdm(range(start, steps), desc="dswm train", unit="step", mininterval=5.0,
                     initial=start, total=steps):
        batch = replay.sample(cfg.batch, cfg.seq_len, gen)
        batch = {k: v.to(model.cells.device) for k, v in batch.items()}
        loss, metrics = model.loss(batch)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.online_parameters(), cfg.grad_clip)
        opt.step()
        model.update_teacher()
        for k in HISTORY_KEYS:
            acc[k] += float(metrics[k])
        n_acc += 1
        if n_acc == window or step + 1 == steps:
            history["step"].append(step + 1)
            for k in HISTORY_KEYS:
                history[f"losses/{k}"].append(acc[k] / n_acc)
            acc, n_acc = {k: 0.0 for k in HISTORY_KEYS}, 0
        if on_step is not None:
            on_step(step + 1)
        if (step + 1) % cfg.checkpoint_every == 0 or step + 1 == steps:
            save_checkpoint(checkpoint, model=model, optimizer=opt, step=step + 1, generator=gen,
                            history=history, extra=extra or {})
    model.eval()
    return history


def save_training_figure(history: dict[str, list[float]], path: str | Path) -> None:
    """The paper's training-diagnostics figure: world-model loss, demand MSE, KL, latent-prediction terms."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    steps = np.asarray(history["step"])
    panels = [("world-model loss", ["losses/loss"]), ("demand MSE (symlog)", ["losses/dem", "losses/cal"]),
              ("KL (free bits)", ["losses/kl", "losses/kl_dyn", "losses/kl_rep"]),
              ("latent prediction", ["losses/lpr_pred", "losses/lpr_var", "losses/h_std"]),
              ("service loss", ["losses/serve"])]
    fig, axes = plt.subplots(1, len(panels), figsize=(4 * len(panels), 3.2))
    for ax, (title, keys) in zip(axes, panels):
        for k in keys:
            ax.plot(steps, history[k], label=k.split("/")[-1])
        ax.set_title(title)
        ax.set_xlabel("gradient step")
        ax.legend(fontsize=7)
        if title != "latent prediction":
            ax.set_yscale("log")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120)
    plt.close(fig)
