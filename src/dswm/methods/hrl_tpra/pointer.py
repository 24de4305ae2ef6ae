"""The high level: a pointer network that assigns each UAV a target cell among the top-N demand cells.

Encoder: every candidate's features are embedded by an MLP, then a set context (the mean embedding, projected) is
added to each, so a candidate's embedding knows the others. Decoder: a GRU cell steps through the UAVs in index
order; at UAV k's step its input is the embedding of the cell chosen at step k - 1 and UAV k's own features (its
fleet features plus a learned index embedding). A pointer (Vinyals et al. 2015; logits C tanh(u), Bello et al.
2016) scores every candidate, u_kj = v . tanh(W_ref e_j + W_q h_k + w_d d_kj) with d_kj UAV k's distance to
candidate j in units of D_max; cells already chosen are masked, so the K choices never repeat (N >= K).

The decoding is serial in K (one small kernel per step): the paper's kernel-launch bound part of the method.
"""
from __future__ import annotations

from typing import NamedTuple

import torch
from torch import nn

from dswm.methods.hrl_tpra.features import CAND_FEATURES, N_FLEET


class Plan(NamedTuple):
    """One decoding of B planner inputs."""

    choice: torch.Tensor
    """(B, K) int64 candidate index chosen for each UAV, no repeats within a row."""
    logp: torch.Tensor
    """(B,) log-probability of the whole assignment (sum of the K conditional log-probabilities)."""
    entropy: torch.Tensor
    """(B,) sum of the K conditional entropies along the decoded path."""


class PointerPlanner(nn.Module):
    """Pointer-network trajectory planner (see the module docstring).

    Args:
        n_uavs: K (decoder steps; one learned index embedding per UAV); hidden: width; tanh_clip: C.
    """

    def __init__(self, *, n_uavs: int, hidden: int, tanh_clip: float):
        super().__init__()
        self.n_uavs, self.tanh_clip = n_uavs, float(tanh_clip)
        self.embed = nn.Sequential(nn.Linear(len(CAND_FEATURES), hidden), nn.ReLU(), nn.Linear(hidden, hidden))
        self.context = nn.Linear(hidden, hidden)
        self.uav = nn.Linear(N_FLEET, hidden)
        self.index = nn.Embedding(n_uavs, hidden)
        self.h0 = nn.Linear(hidden, hidden)
        self.start = nn.Parameter(torch.zeros(hidden))
        self.gru = nn.GRUCell(2 * hidden, hidden)
        self.w_ref = nn.Linear(hidden, hidden, bias=False)
        self.w_q = nn.Linear(hidden, hidden)
        self.w_d = nn.Parameter(torch.zeros(hidden))
        self.v = nn.Parameter(torch.empty(hidden).uniform_(-hidden ** -0.5, hidden ** -0.5))

    def encode(self, cand: torch.Tensor) -> torch.Tensor:
        """(B, N, H) candidate embeddings of features (B, N, F)."""
        e = self.embed(cand)
        return e + self.context(e.mean(dim=1, keepdim=True))

    def forward(self, cand: torch.Tensor, uav: torch.Tensor, dist: torch.Tensor, *, choice: torch.Tensor | None = None,
                greedy: bool = False, generator: torch.Generator | None = None) -> Plan:
        """Decode an assignment, or score a given one.

        Args:
            cand: (B, N, F) candidate features; uav: (B, K, 7) fleet features; dist: (B, K, N) in units of D_max.
            choice: (B, K) an assignment to score (teacher forcing); None to decode one.
            greedy: decode by the largest probability at each step (else sample with ``generator``).

        Returns:
            :class:`Plan`.
        """
        b, n, _ = cand.shape
        k = uav.shape[1]
        if n < k:
            raise ValueError(f"pointer: {n} candidates for {k} UAVs; it needs at least one distinct cell per UAV")
        e = self.encode(cand)
        ref = self.w_ref(e)  # (B, N, H)
        query_in = self.uav(uav) + self.index.weight[:k].unsqueeze(0)  # (B, K, H)
        h = torch.tanh(self.h0(e.mean(dim=1)))
        prev = self.start.expand(b, -1)
        taken = torch.zeros(b, n, dtype=torch.bool, device=cand.device)
        rows = torch.arange(b, device=cand.device)
        picks, logp, entropy = [], cand.new_zeros(b), cand.new_zeros(b)
        for step in range(k):
            h = self.gru(torch.cat([prev, query_in[:, step]], dim=-1), h)
            u = torch.tanh(ref + self.w_q(h).unsqueeze(1) + dist[:, step].unsqueeze(-1) * self.w_d) @ self.v  # (B, N)
            logits = (self.tanh_clip * torch.tanh(u)).masked_fill(taken, float("-inf"))
            logq = torch.log_softmax(logits, dim=-1)
            if choice is not None:
                pick = choice[:, step]
            elif greedy:
                pick = logq.argmax(dim=-1)
            else:
                pick = torch.multinomial(logq.exp().cpu(), 1, generator=generator).squeeze(-1).to(cand.device)
            logp = logp + logq[rows, pick]
            entropy = entropy - (logq.exp() * logq.masked_fill(taken, 0.0)).sum(-1)  # 0 log 0 = 0, no NaN gradient
            taken = taken.clone()
            taken[rows, pick] = True
            prev = e[rows, pick]
            picks.append(pick)
        return Plan(choice=torch.stack(picks, dim=1), logp=logp, entropy=entropy)


class PlanCritic(nn.Module):
    """V(s) of a macro-slot's start from the planner's flat summary: the REINFORCE baseline and bootstrap."""

    def __init__(self, *, in_dim: int, hidden: int):
        super().__init__()
        self.net = nn.Sequential(nn.Linear(in_dim, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
                                 nn.Linear(hidden, 1))

    def forward(self, summary: torch.Tensor) -> torch.Tensor:
        """(B,) values of summaries (B, in_dim)."""
        return self.net(summary).squeeze(-1)
