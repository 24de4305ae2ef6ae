"""Building blocks of the DSWM world model that do not touch the service physics.

Observation encoder (any grid), the E-head demand ensemble in symlog space, the latent predictor g(h) of the
latent predictive regularization, the SR-MLP head of the ``dswm_wo_dec`` ablation, the EMA teacher update
(eq. 13) and the per-dimension variance margin (eq. 14).
"""
from __future__ import annotations

import math

import torch
from torch import nn
from torch.nn import functional as F


def symlog(x: torch.Tensor) -> torch.Tensor:
    """sign(x) ln(1 + |x|)."""
    return torch.sign(x) * torch.log1p(torch.abs(x))


def symexp(y: torch.Tensor) -> torch.Tensor:
    """Inverse of ``symlog``: sign(y) (exp(|y|) - 1)."""
    return torch.sign(y) * torch.expm1(torch.abs(y))


class ObsEncoder(nn.Module):
    """e_psi(o_t): demand window on any grid + fleet state + time phase -> embedding.

    Two stride-2 convs read the window's spatial pattern on any grid size (the model is trained per
    dataset, so the flattened conv output size follows from the grid; stride 2 twice because the encoder
    is the largest cost of a training step); a linear
    map of the newest map keeps cell-level detail (the model is trained per dataset, so the grid is known);
    the fleet (K, 7) and the time phase (2,) enter through an MLP.
    """

    def __init__(self, *, window: int, rows: int, cols: int, n_uavs: int, embed: int, channels: int):
        super().__init__()
        c = channels
        self.conv = nn.Sequential(
            nn.Conv2d(window, c, 3, stride=2, padding=1), nn.ELU(),
            nn.Conv2d(c, 2 * c, 3, stride=2, padding=1), nn.ELU(), nn.Flatten())
        conv_out = 2 * c * ((rows + 3) // 4) * ((cols + 3) // 4)   # 5x5 for 20x20, 3x3 for 9x9
        self.last_map = nn.Linear(rows * cols, embed)
        self.fleet = nn.Sequential(nn.Linear(n_uavs * 7 + 2, embed), nn.ELU())
        self.out = nn.Sequential(nn.Linear(conv_out + 2 * embed, embed), nn.LayerNorm(embed), nn.ELU())
        # Normalizer of symlog demand (set from the training replay; saved in every checkpoint).
        self.register_buffer("dem_mean", torch.zeros(()))
        self.register_buffer("dem_std", torch.ones(()))

    def forward(self, demand_symlog: torch.Tensor, fleet: torch.Tensor, time: torch.Tensor) -> torch.Tensor:
        """Args: symlog(demand) (B, W, R, C), fleet (B, K, 7), time (B, 2).  Returns: (B, embed)."""
        d = (demand_symlog - self.dem_mean) / self.dem_std
        spatial = self.conv(d)                                            # (B, 2c * pooled^2)
        last = F.elu(self.last_map(d[:, -1].flatten(1)))                  # (B, embed)
        fl = self.fleet(torch.cat([fleet.flatten(1), time], -1))          # (B, embed)
        return self.out(torch.cat([spatial, last, fl], -1))


class DemandEnsemble(nn.Module):
    """E independent heads D_e(h, z) -> next-slot demand map in symlog space, each a low-rank decoder.

    Head e: coefficients c_e = W2_e elu(W1_e f + b1_e) + b2_e (rank r), map = c_e @ basis_e + bias_e (G cells).
    All heads run as one batched einsum, so planning cost is O(N E (F H + r G)).
    """

    def __init__(self, *, feat_dim: int, n_heads: int, hidden: int, rank: int, n_cells: int):
        super().__init__()
        e = n_heads

        def init(*shape, fan_in):
            return nn.Parameter(torch.empty(*shape).uniform_(-1, 1) / math.sqrt(fan_in))

        self.w1, self.b1 = init(e, feat_dim, hidden, fan_in=feat_dim), nn.Parameter(torch.zeros(e, hidden))
        self.w2, self.b2 = init(e, hidden, rank, fan_in=hidden), nn.Parameter(torch.zeros(e, rank))
        self.basis = init(e, rank, n_cells, fan_in=rank)
        self.bias = nn.Parameter(torch.zeros(e, n_cells))

    def forward(self, feat: torch.Tensor, *, heads_first: bool = False) -> torch.Tensor:
        """Args: feat (N, F).  Returns: symlog demand of every head, (N, E, G), or (E, N, G) if heads_first
        (the planner's layout: reductions over heads then run over the leading, contiguous axis)."""
        if heads_first:
            h = F.elu(torch.einsum("nf,efh->enh", feat, self.w1) + self.b1.unsqueeze(1))
            coef = torch.einsum("enh,ehr->enr", h, self.w2) + self.b2.unsqueeze(1)
            return torch.baddbmm(self.bias.unsqueeze(1), coef, self.basis)
        h = F.elu(torch.einsum("nf,efh->neh", feat, self.w1) + self.b1)
        coef = torch.einsum("neh,ehr->ner", h, self.w2) + self.b2
        return torch.einsum("ner,erg->neg", coef, self.basis) + self.bias

    @torch.no_grad()
    def init_bias(self, mean_symlog_map: torch.Tensor) -> None:
        """Start every head at the training mean map (G,) in symlog space."""
        self.bias.copy_(mean_symlog_map.to(self.bias).expand_as(self.bias))


def mlp(inp: int, hidden: int, out: int) -> nn.Sequential:
    """Two-layer ELU MLP."""
    return nn.Sequential(nn.Linear(inp, hidden), nn.ELU(), nn.Linear(hidden, hidden), nn.ELU(),
                         nn.Linear(hidden, out))


class SRHead(nn.Module):
    """``dswm_wo_dec``: served ratio regressed directly from the latent feature, (N, F) -> (N,) in (0, 1)."""

    def __init__(self, *, feat_dim: int, hidden: int):
        super().__init__()
        self.net = mlp(feat_dim, hidden, 1)

    def forward(self, feat: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(self.net(feat).squeeze(-1))


@torch.no_grad()
def ema_update(teacher: nn.Module, student: nn.Module, nu: float) -> None:
    """theta_bar <- nu * theta_bar + (1 - nu) * theta (eq. 13), in place; buffers are copied.

    Args:
        teacher, student: modules of identical structure; nu: EMA coefficient in [0, 1].
    """
    for p_t, p_s in zip(teacher.parameters(), student.parameters(), strict=True):
        p_t.mul_(nu).add_(p_s.detach(), alpha=1.0 - nu)
    for b_t, b_s in zip(teacher.buffers(), student.buffers(), strict=True):
        b_t.copy_(b_s)


def variance_margin(h: torch.Tensor, margin: float, eps: float = 1e-4) -> torch.Tensor:
    """sum_j max(0, margin - Std_j(h)) with the std over the batch (second term of eq. 14).

    Args:
        h: (N, D) latent vectors, N >= 2; margin: m_var; eps: keeps the sqrt differentiable at 0.
    Returns:
        Scalar penalty.
    """
    std = torch.sqrt(h.var(dim=0) + eps)
    return F.relu(margin - std).sum()
