"""The DSWM world model: encoder + RSSM + demand ensemble + LPR (EMA teacher) + service head, and its loss.

Loss (eq. 15 plus the ensemble's calibration term), on replayed sequences of length T and batch B:
    L_WM = L_dem + lambda_cal L_cal + beta_KL L_KL + lambda_L L_LPR + lambda_serve L_serve
- L_dem: symlog MSE of each of the E heads' next-slot map, decoded from the PRIOR state at t+1
  (h_{t+1} = f(h_t, z_t, a_t), z_{t+1} ~ p(z | h_{t+1})), exactly what imagination decodes at planning time.
- L_cal: the ensemble spread Std_e matches the (stopped) error of the ensemble mean, per cell.
- L_KL: balanced free-bits KL (``RSSM.kl_loss``).
- L_LPR: ||g(h_t) - sg[h_bar_{t+1}]||^2 with h_bar from the EMA teacher, plus lambda_var * variance margin.
- L_serve: (SR_hat_{t+1} - SR_{t+1})^2; SR_hat is ``dswm.sim.physics.served_ratio`` applied to the predicted map
  at the replayed next positions (decomposed head), or the SR-MLP on the latent (``dswm_wo_dec``).
"""
from __future__ import annotations

import copy
import dataclasses
import math
from typing import Any, Literal, Mapping

import torch
from torch import nn
from torch.nn import functional as F

from dswm.config import ENUM, FLAT, build, check_fields, setting
from dswm.sim.physics import ServiceParams, associate, served_ratio, service
from dswm.methods.dswm.rssm import RSSM, LatentState, RSSMConfig, map_state
from dswm.methods.dswm.modules import (DemandEnsemble, ObsEncoder, SRHead, ema_update, mlp, symlog,
                             variance_margin)

DEMAND_FLOOR = 1e-4
"""Predicted demand below this (normalized units; the training p99 is 1) is set to exactly 0: the service
physics then treats the cell as empty, and the bandwidth weight x^tau keeps a finite gradient."""


_FLOOR_SYMLOG = math.log1p(DEMAND_FLOOR)


def to_demand(pred: torch.Tensor) -> torch.Tensor:
    """Symlog predictions (...) -> non-negative demand, values under ``DEMAND_FLOOR`` set to 0.

    Equal to ``where(symexp(pred) > DEMAND_FLOOR, symexp(pred), 0)``, written as three cheap passes (this runs
    on N_cem x E x G values per imagined step): exp(.) - 1 instead of expm1, which is several times slower on
    CPU; its absolute error (about 1e-7 in normalized units) is far below DEMAND_FLOOR."""
    return torch.exp(F.threshold(pred, _FLOOR_SYMLOG, 0.0)) - 1.0


@dataclasses.dataclass(frozen=True, kw_only=True)
class WorldModelConfig:
    """World-model sizes and loss weights (values and reasons in config.yaml ``dswm.world_model``)."""

    rssm: RSSMConfig = setting(FLAT)
    """The RSSM's sizes and KL settings, whose keys sit in ``dswm.world_model`` itself (:meth:`from_flat`)."""
    ensemble: int = setting("count")
    """E, demand heads."""
    demand_hidden: int = setting("count")
    """Hidden width of each demand head."""
    demand_rank: int = setting("count")
    """Rank of each head's low-rank map decoder."""
    enc_channels: int = setting("count")
    """Conv channels of the encoder's first layer."""
    head_hidden: int = setting("count")
    """Width of the latent predictor g and of the SR-MLP head."""
    ema_nu: float = setting("fraction")
    """nu, EMA coefficient of the teacher."""
    lambda_var: float = setting("nonnegative")
    """lambda_var, weight of the LPR variance margin."""
    m_var: float = setting("nonnegative")
    """m_var, the margin the per-dimension std of the GRU state h is kept above."""
    beta_kl: float = setting("nonnegative")
    """beta_KL, weight of the KL term L_KL."""
    lambda_lpr: float = setting("nonnegative")
    """lambda_L, weight of the latent-prediction term L_LPR."""
    lambda_cal: float = setting("nonnegative")
    """lambda_cal, weight of the ensemble calibration term L_cal."""
    lambda_serve: float = setting("nonnegative")
    """lambda_serve, weight of the service term L_serve."""
    service_head: Literal["physics", "mlp"] = setting(ENUM)
    """"physics" (decomposed head, eq. 16) or "mlp" (the dswm_wo_dec ablation)."""

    def __post_init__(self):
        check_fields(self, "dswm.world_model")

    @classmethod
    def from_flat(cls, section: Mapping[str, Any], where: str) -> "WorldModelConfig":
        """Build from config.yaml's flat ``dswm.world_model`` section: the RSSM's keys go to ``rssm``."""
        rssm_keys = {f.name for f in dataclasses.fields(RSSMConfig)}
        rssm = build(RSSMConfig, {k: v for k, v in section.items() if k in rssm_keys}, where)
        return build(cls, {k: v for k, v in section.items() if k not in rssm_keys}, where, rssm=rssm)


class WorldModel(nn.Module):
    """Encoder-RSSM stack with its heads; ``teacher`` is the EMA copy of (encoder, rssm)."""

    def __init__(self, *, cfg: WorldModelConfig, rows: int, cols: int, n_uavs: int, window: int,
                 cells: torch.Tensor, params: ServiceParams):
        super().__init__()
        self.cfg, self.params = cfg, params
        self.rows, self.cols, self.n_uavs = rows, cols, n_uavs
        r = cfg.rssm
        self.encoder = ObsEncoder(window=window, rows=rows, cols=cols, n_uavs=n_uavs, embed=r.embed,
                                  channels=cfg.enc_channels)
        self.rssm = RSSM(cfg=r, action_dim=3 * n_uavs)
        feat = self.rssm.feat_dim
        self.demand = DemandEnsemble(feat_dim=feat, n_heads=cfg.ensemble, hidden=cfg.demand_hidden,
                                     rank=cfg.demand_rank, n_cells=rows * cols)
        self.predictor = mlp(r.deter, cfg.head_hidden, r.deter)
        self.sr_head = SRHead(feat_dim=feat, hidden=cfg.head_hidden) if cfg.service_head == "mlp" else None
        self.register_buffer("cells", cells.to(torch.float32).clone())
        self.teacher = nn.ModuleDict({"encoder": copy.deepcopy(self.encoder), "rssm": copy.deepcopy(self.rssm)})
        self.teacher.requires_grad_(False)

    def online_parameters(self) -> list[nn.Parameter]:
        """Parameters trained by gradient (everything except the EMA teacher)."""
        return [p for n, p in self.named_parameters() if not n.startswith("teacher.")]

    def update_teacher(self) -> None:
        """EMA update of the teacher after a gradient step (eq. 13)."""
        ema_update(self.teacher["encoder"], self.encoder, self.cfg.ema_nu)
        ema_update(self.teacher["rssm"], self.rssm, self.cfg.ema_nu)

    @torch.no_grad()
    def set_normalizer(self, demand: torch.Tensor) -> None:
        """Fit the demand normalizer and the ensemble's bias from training maps (D, T, R, C)."""
        y = symlog(demand.float())
        for enc in (self.encoder, self.teacher["encoder"]):
            enc.dem_mean.copy_(y.mean())
            enc.dem_std.copy_(y.std().clamp_min(1e-3))
        self.demand.init_bias(y.reshape(-1, self.rows * self.cols).mean(0))

    # ---- pieces used by training and by the planner ---------------------------------------------------
    def embed(self, demand_symlog: torch.Tensor, fleet: torch.Tensor, time: torch.Tensor, *,
              teacher: bool = False):
        """Embed observations with any leading axes L: symlog(demand) (L.., W, R, C), fleet (L.., K, 7),
        time (L.., 2) -> (L.., embed)."""
        lead = demand_symlog.shape[:-3]
        enc = self.teacher["encoder"] if teacher else self.encoder
        out = enc(demand_symlog.reshape(-1, *demand_symlog.shape[-3:]), fleet.reshape(-1, *fleet.shape[-2:]),
                  time.reshape(-1, 2))
        return out.reshape(*lead, -1)

    def demand_members(self, feat: torch.Tensor) -> torch.Tensor:
        """Non-negative demand of every head, heads first: (E, N, G), from features (N, F)."""
        return to_demand(self.demand(feat, heads_first=True))

    def service_sr(self, feat: torch.Tensor, demand: torch.Tensor, pos: torch.Tensor, avail: torch.Tensor,
                   bw_logit: torch.Tensor) -> torch.Tensor:
        """SR_hat (N,) of demand (N, G) at positions (N, K, 2) with availability (N, K) and logits (N, K).

        The decomposed head calls the project's one physics implementation; the ``mlp`` head ignores the
        physical arguments and regresses SR from the latent feature (N, F).
        """
        if self.sr_head is not None:
            return self.sr_head(feat)
        return served_ratio(demand, pos, avail, self.cells, params=self.params, bw_logit=bw_logit)

    def serve(self, feat: torch.Tensor, demand: torch.Tensor, pos: torch.Tensor, avail: torch.Tensor,
              bw_logit: torch.Tensor, *, need_assoc: bool = False) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Planning-time service head: (SR_hat (N,), association (N, G) or None).

        The physics head's association comes with its SR; the SR-MLP head computes one only when asked.
        """
        if self.sr_head is not None:
            assoc = associate(pos, avail, self.cells) if need_assoc else None
            return self.sr_head(feat), assoc
        res = service(demand, pos, avail, self.cells, params=self.params, bw_logit=bw_logit)
        return res.sr, res.assoc

    # ---- training loss ---------------------------------------------------------------------------------
    def loss(self, batch: dict[str, torch.Tensor]) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """World-model loss on a batch of sequences.

        Args:
            batch: ``demand`` (T, B, W, R, C), ``fleet`` (T, B, K, 7), ``time`` (T, B, 2), ``prev_action`` and
                ``action`` (T, B, K, 3), ``next_demand`` (T, B, R, C), ``next_pos`` (T, B, K, 2),
                ``next_avail`` (T, B, K) bool, ``next_sr`` (T, B).
        Returns:
            (total loss, metrics dict of detached scalars: loss, dem, cal, kl, kl_dyn, kl_rep, lpr_pred,
            lpr_var, serve, h_std).
        """
        cfg = self.cfg
        t_len, b = batch["time"].shape[:2]
        prev_a = batch["prev_action"].flatten(2)                        # (T, B, A)
        act = batch["action"].flatten(2)                                # (T, B, A)
        dsym = symlog(batch["demand"])                                  # (T, B, W, R, C)
        embeds = self.embed(dsym, batch["fleet"], batch["time"])        # (T, B, E)
        init = self.rssm.initial(b, device=embeds.device)
        posts, priors = self.rssm.observe(embeds, prev_a, init)        # fields (T, B, .)

        # Next-slot prior from every posterior (what imagination decodes): (T*B, .)
        flat_post = map_state(posts, lambda x: x.reshape(t_len * b, -1))
        nxt = self.rssm.img_step(flat_post, act.reshape(t_len * b, -1))
        feat_next = self.rssm.feat(nxt)                                 # (TB, F)

        # Demand ensemble in symlog space and its calibration.
        pred = self.demand(feat_next)                                   # (TB, E, G)
        target = symlog(batch["next_demand"].reshape(t_len * b, -1))    # (TB, G)
        l_dem = ((pred - target.unsqueeze(1)) ** 2).mean()
        mean_pred = pred.mean(1)                                        # (TB, G)
        # population std over heads, written out: std(dim=1) of (TB, E, G) is far slower on CPU
        spread = ((pred - mean_pred.unsqueeze(1)).square().mean(1) + 1e-8).sqrt()
        err = (mean_pred - target).abs().detach()
        l_cal = ((spread - err) ** 2).mean()

        # Service head on the replayed next positions.
        x_hat = to_demand(pred).mean(1)                                 # (TB, G)
        pos = batch["next_pos"].reshape(t_len * b, self.n_uavs, 2)
        avail = batch["next_avail"].reshape(t_len * b, self.n_uavs)
        bw = act.reshape(t_len * b, self.n_uavs, 3)[..., 2]
        sr_hat = self.service_sr(feat_next, x_hat, pos, avail, bw)
        l_serve = ((sr_hat - batch["next_sr"].reshape(-1)) ** 2).mean()

        # KL with balancing and free bits.
        l_kl, kl_info = self.rssm.kl_loss(posts, priors)

        # Latent predictive regularization: predictor vs EMA teacher, plus the variance margin.
        with torch.no_grad():
            t_emb = self.embed(dsym, batch["fleet"], batch["time"], teacher=True)
            t_posts, _ = self.teacher["rssm"].observe(t_emb, prev_a, init, sample=False)
        h = posts.deter                                                 # (T, B, D)
        l_pred = ((self.predictor(h[:-1]) - t_posts.deter[1:]) ** 2).sum(-1).mean()
        l_var = variance_margin(h.reshape(t_len * b, -1), cfg.m_var)
        l_lpr = l_pred + cfg.lambda_var * l_var

        total = (l_dem + cfg.lambda_cal * l_cal + cfg.beta_kl * l_kl + cfg.lambda_lpr * l_lpr
                 + cfg.lambda_serve * l_serve)
        metrics = {"loss": total, "dem": l_dem, "cal": l_cal, "kl": kl_info["kl"], "kl_dyn": kl_info["kl_dyn"],
                   "kl_rep": kl_info["kl_rep"], "lpr_pred": l_pred, "lpr_var": l_var, "serve": l_serve,
                   "h_std": h.reshape(t_len * b, -1).std(0).mean()}
        return total, {k: v.detach() for k, v in metrics.items()}

    # ---- filtering at decision time --------------------------------------------------------------------
    @torch.no_grad()
    def filter_step(self, state: LatentState, prev_action: torch.Tensor, demand: torch.Tensor,
                    fleet: torch.Tensor, time: torch.Tensor) -> LatentState:
        """Posterior update with one observation (batch 1 or more); uses posterior means (no sampling).

        Args: state (B, .); prev_action (B, K, 3); demand (B, W, R, C); fleet (B, K, 7); time (B, 2).
        Returns: posterior state at t, (B, .).
        """
        emb = self.embed(symlog(demand), fleet, time)
        post, _ = self.rssm.obs_step(state, prev_action.flatten(1), emb, sample=False)
        return post
