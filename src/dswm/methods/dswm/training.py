"""Offline training of the DSWM world model (paper Algorithm 2).

1. Heuristic pre-collection on the TRAINING-days core only (every episode records its tensor day index;
   ``dswm.methods.collect.collect``, with the collection keys of ``dswm.training``).
2. Gradient steps on replayed sequences with the loss of eq. 15 plus the ensemble calibration term
   (``WorldModel.loss``), Adam at the configured learning rate, EMA teacher update after every step.
3. Complete checkpoints (weights incl. teacher and normalizer buffers, optimizer, RNG states, step, history),
   written atomically; ``train`` resumes from one and reproduces the very next losses.
The loss history is returned as arrays ({"losses/<term>": [...], "step": [...]}) for MLflow batch logging and
drawn by ``save_training_figure`` as the training-diagnostics figure.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Callable, ClassVar

import numpy as np
import torch
from tqdm import tqdm

from prep.atomic import atomic_path
from dswm.config import setting
from dswm.methods.collect import CollectSettings
from dswm.methods.dswm.world_model import WorldModel
from dswm.methods.replay import SequenceReplay

HISTORY_KEYS = ("loss", "dem", "cal", "kl", "kl_dyn", "kl_rep", "lpr_pred", "lpr_var", "serve", "h_std")


@dataclasses.dataclass(frozen=True, kw_only=True)
class TrainConfig(CollectSettings):
    """Optimization and pre-collection settings (values and reasons in config.yaml ``dswm.training``); the
    pre-collection's fields are ``CollectSettings``' (``dswm.methods.collect.collect`` takes this whole config)."""

    section: ClassVar[str] = "dswm.training"

    lr: float = setting("positive")
    """Adam's learning rate."""
    batch: int = setting("count")
    """Sequences per gradient step."""
    seq_len: int = setting("count")
    """Decisions per replayed sequence."""
    grad_clip: float = setting("positive")
    """Global gradient-norm clip."""
    log_points: int = setting("count")
    """Number of points of the loss history (averages over equal windows of steps)."""
    checkpoint_every: int = setting("count")
    """Gradient steps between checkpoints (the last step always writes one)."""
    compile: bool = setting("flag")
    """Compute the loss and its gradient as code compiled by ``torch.compile`` (:func:`loss_function`)."""


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


def loss_function(model: WorldModel, compile: bool) -> Callable:
    """``model.loss``, or with ``compile`` that method compiled by ``torch.compile``: the same loss on the same
    batch, its element-wise work fused into a few loops and the backward pass compiled with it (AOTAutograd). The
    first call in a process compiles (one to two minutes at the paper's sizes); the floats differ from the eager
    loss's in the last bits, and its Gaussian draws come from the compiled code's own generator, seeded from torch's
    (so a seed still gives the same run)."""
    return torch.compile(model.loss, dynamic=False) if compile else model.loss


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
    loss_of = loss_function(model, cfg.compile)
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
        loss, metrics = loss_of(batch)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.online_parameters(), cfg.grad_clip)
        opt.step()
        model.update_teacher()
        for k, v in zip(HISTORY_KEYS, torch.stack([metrics[k] for k in HISTORY_KEYS]).tolist()):  # one read
            acc[k] += v
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
