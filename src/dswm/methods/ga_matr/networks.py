"""GA-MATR's inputs and networks: UAV tokens, demand-context tokens, masked graph attention, the critic.

Observations are the environment's: demand (N, w+1, R, C), fleet (N, K, 7), time (N, 2). Demand enters every
network as log1p(x) (the fixed transform of ``dswm.methods.rl.spaces``).

* UAV token k (:func:`policy_inputs`): a (2 r + 1)^2 crop of the w+1 log1p maps centred on UAV k's cell (zero
  outside the area), its own fleet features (7) and the time phase (2); a linear layer maps it to d_model and a
  learned embedding of the index k is added (the symmetry breaking of the paper's lesson 1).
* Demand-context tokens: the w+1 log1p maps pooled to a P x P grid, mean and max per block, with the block's
  centre (x / W, y / H); P^2 tokens, each mapped to d_model.
* Attention mask: UAV j is a key of UAV i's self-attention only if j is available (active: not returning, not
  charging) or j = i. An unavailable UAV thus receives no attention weight and its features change nothing in
  the others' outputs; its own token still attends to the available UAVs, to itself and to the context (its
  action does nothing while it is unavailable).
* Products: with ``matmul_dtype`` bfloat16 (:mod:`dswm.methods.matmul`'s names) the tokens and the blocks run under
  torch's autocast: their matrix products in bfloat16 with float32 accumulation, each added to the float32 residual
  stream; the layer norms, the attention's softmax, the heads, the critic, the weights and their gradients stay
  float32. ``float32`` computes every operation as before the setting existed, bit for bit.
* Critic: an MLP on the flat global observation (``dswm.methods.rl.spaces.flat_observation``: every map, every
  UAV's fleet features, the time phase), outputting the value in the value normalizer's units.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import nn
from torch.nn import functional as F

from dswm.methods.matmul import MatmulDtype, autocast

N_ACTION = 3
"""(dx, dy, bw_logit) per UAV."""
N_FLEET = 7
"""Fleet features per UAV (``dswm.sim.core.FLEET_FEATURES``); index 3 is "active"."""
ACTIVE_FEATURE = 3


class PolicyInputs(NamedTuple):
    """What the policy reads, one entry per observation."""

    uav: torch.Tensor  # (N, K, uav_dim) crop, own fleet features, time
    context: torch.Tensor  # (N, P^2, context_dim) pooled maps and block centres
    available: torch.Tensor  # (N, K) bool: the UAV is active (can serve, its action moves it)


def uav_dim(maps: int, radius: int) -> int:
    """Width of a UAV token's input: ``maps`` (= w+1) channels over (2 r + 1)^2 cells, own fleet features, time."""
    return maps * (2 * radius + 1) ** 2 + N_FLEET + 2


def context_dim(maps: int) -> int:
    """Width of a context token's input: mean and max of ``maps`` channels over the block, and its centre."""
    return 2 * maps + 2


def local_crops(maps: torch.Tensor, fleet: torch.Tensor, radius: int) -> torch.Tensor:
    """(N, K, C * S * S) crops of side S = 2 r + 1 of ``maps`` (N, C, R, Cols) centred on each UAV's cell.

    A UAV's cell is (floor(y/H * R), floor(x/W * Cols)), row 0 south; cells outside the area read 0.
    """
    n, c, rows, cols = maps.shape
    k, side = fleet.shape[1], 2 * radius + 1
    col = torch.clamp((fleet[..., 0] * cols).floor().long(), 0, cols - 1)
    row = torch.clamp((fleet[..., 1] * rows).floor().long(), 0, rows - 1)
    padded = F.pad(maps, (radius, radius, radius, radius)).reshape(n, c, -1)  # (N, C, (R+2r)(Cols+2r))
    offs = torch.arange(side, device=maps.device)
    flat = (row.unsqueeze(-1) + offs).unsqueeze(-1) * (cols + 2 * radius) + (col.unsqueeze(-1) + offs).unsqueeze(-2)
    crop = padded.gather(2, flat.reshape(n, 1, k * side * side).expand(n, c, -1))  # (N, C, K S S)
    return crop.reshape(n, c, k, side * side).permute(0, 2, 1, 3).reshape(n, k, c * side * side)


def context_tokens(maps: torch.Tensor, side: int) -> torch.Tensor:
    """(N, P^2, 2 C + 2): mean and max of ``maps`` (N, C, R, Cols) over a P x P grid of blocks, and each block's
    centre (x / W, y / H); blocks row-major from the south-west."""
    n = maps.shape[0]
    pooled = torch.cat([F.adaptive_avg_pool2d(maps, side), F.adaptive_max_pool2d(maps, side)], dim=1)
    centre = (torch.arange(side, dtype=maps.dtype, device=maps.device) + 0.5) / side
    yy, xx = torch.meshgrid(centre, centre, indexing="ij")
    where = torch.stack([xx, yy], dim=-1).reshape(1, side * side, 2).expand(n, -1, -1)
    return torch.cat([pooled.flatten(2).transpose(1, 2), where], dim=-1)


def policy_inputs(demand: torch.Tensor, fleet: torch.Tensor, time: torch.Tensor, *, radius: int,
                  side: int) -> PolicyInputs:
    """The policy's inputs of raw observations: demand (N, w+1, R, C), fleet (N, K, 7), time (N, 2)."""
    maps = torch.log1p(demand)
    k = fleet.shape[1]
    uav = torch.cat([local_crops(maps, fleet, radius), fleet, time.unsqueeze(1).expand(-1, k, -1)], dim=-1)
    return PolicyInputs(uav=uav, context=context_tokens(maps, side), available=fleet[..., ACTIVE_FEATURE] > 0.5)


def attention_mask(available: torch.Tensor) -> torch.Tensor:
    """(N, K, K) bool: entry (i, j) is True when UAV i may attend to UAV j (j available, or j = i)."""
    k = available.shape[-1]
    eye = torch.eye(k, dtype=torch.bool, device=available.device)
    return available.unsqueeze(-2) | eye


class Attention(nn.Module):
    """Multi-head scaled dot-product attention of queries ``x`` (N, L, d) over keys/values ``y`` (N, S, d)."""

    def __init__(self, d_model: int, heads: int):
        super().__init__()
        self.heads = heads
        self.query = nn.Linear(d_model, d_model)
        self.key_value = nn.Linear(d_model, 2 * d_model)
        self.out = nn.Linear(d_model, d_model)

    def forward(self, x: torch.Tensor, y: torch.Tensor,
                allowed: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Output (N, L, d) and the attention weights (N, heads, L, S); keys with ``allowed`` (N, L, S) False get
        weight exactly 0 (every row must allow one key)."""
        n, length, d = x.shape
        h = self.heads
        q = self.query(x).view(n, length, h, d // h).transpose(1, 2)  # (N, H, L, dh)
        k, v = self.key_value(y).view(n, y.shape[1], 2, h, d // h).permute(2, 0, 3, 1, 4)  # (N, H, S, dh) each
        scores = q @ k.transpose(-1, -2) / math.sqrt(d // h)
        if allowed is not None:
            scores = scores.masked_fill(~allowed.unsqueeze(1), float("-inf"))
        weights = torch.softmax(scores, dim=-1, dtype=torch.float32)  # float32 under autocast too
        return self.out((weights @ v).transpose(1, 2).reshape(n, length, d)), weights


class GraphAttentionBlock(nn.Module):
    """Pre-norm residual block: masked self-attention among UAV tokens, cross-attention from UAV tokens to the
    demand-context tokens, feed-forward."""

    def __init__(self, d_model: int, heads: int, ffn_hidden: int):
        super().__init__()
        self.norm_self, self.norm_cross, self.norm_ffn = (nn.LayerNorm(d_model) for _ in range(3))
        self.self_attn = Attention(d_model, heads)
        self.cross_attn = Attention(d_model, heads)
        self.ffn = nn.Sequential(nn.Linear(d_model, ffn_hidden), nn.ReLU(), nn.Linear(ffn_hidden, d_model))

    def forward(self, h: torch.Tensor, context: torch.Tensor, allowed: torch.Tensor) -> tuple[torch.Tensor, dict]:
        """h (N, K, d), context (N, S, d) (already normalized), allowed (N, K, K); returns h and the weights."""
        x = self.norm_self(h)
        out, w_self = self.self_attn(x, x, allowed)
        h = h + out
        out, w_cross = self.cross_attn(self.norm_cross(h), context)
        h = h + out
        h = h + self.ffn(self.norm_ffn(h))
        return h, {"self": w_self, "cross": w_cross}


class GraphAttentionPolicy(nn.Module):
    """The policy shared by the K UAVs: tokens -> graph-attention blocks -> per-UAV Gaussian over (dx, dy, bw).

    The mean is tanh of a linear head on each UAV's final embedding (so it lies in (-1, 1)); the std is
    state-independent, one learned value per agent and action component. Samples are clipped to [-1, 1] by the
    environment (and by the controller); log-probabilities are those of the unclipped sample.
    """

    def __init__(self, *, n_agents: int, uav_in: int, context_in: int, d_model: int, heads: int, layers: int,
                 ffn_hidden: int, init_std: float, matmul_dtype: MatmulDtype = "float32"):
        super().__init__()
        self.matmul_dtype = matmul_dtype
        self.uav_in = nn.Linear(uav_in, d_model)
        self.index = nn.Embedding(n_agents, d_model)
        self.context_in = nn.Linear(context_in, d_model)
        self.context_norm = nn.LayerNorm(d_model)
        self.blocks = nn.ModuleList(GraphAttentionBlock(d_model, heads, ffn_hidden) for _ in range(layers))
        self.final_norm = nn.LayerNorm(d_model)
        self.mean_head = nn.Linear(d_model, N_ACTION)
        nn.init.orthogonal_(self.mean_head.weight, gain=0.01)
        nn.init.zeros_(self.mean_head.bias)
        self.log_std = nn.Parameter(torch.full((n_agents, N_ACTION), math.log(init_std)))

    def embed(self, x: PolicyInputs, *, return_weights: bool = False):
        """(N, K, d) final per-UAV embeddings (after the last LayerNorm); with ``return_weights`` also the list of
        each block's attention weights. With ``matmul_dtype`` bfloat16 the tokens and the blocks run under autocast:
        their products in bfloat16, each added to the float32 residual stream."""
        with autocast(x.uav.device.type, self.matmul_dtype):
            h = self.uav_in(x.uav) + self.index.weight.unsqueeze(0)
            context = self.context_norm(self.context_in(x.context).float())
            allowed = attention_mask(x.available)
            weights = []
            for block in self.blocks:
                h, w = block(h, context, allowed)
                weights.append(w)
        h = self.final_norm(h)
        return (h, weights) if return_weights else h

    def forward(self, x: PolicyInputs) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Mean (N, K, 3) in (-1, 1), std (K, 3) and the embeddings (N, K, d)."""
        emb = self.embed(x)
        return torch.tanh(self.mean_head(emb)), self.log_std.exp(), emb


def log_prob(mean: torch.Tensor, std: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """(N, K) log-density of the unclipped actions (N, K, 3) under independent Gaussians (mean (N, K, 3), std
    (K, 3)), summed over the 3 components."""
    z = (action - mean) / std
    return (-0.5 * z.pow(2) - torch.log(std) - 0.5 * math.log(2 * math.pi)).sum(-1)


def entropy(std: torch.Tensor) -> torch.Tensor:
    """(K,) entropy of each agent's Gaussian (std (K, 3))."""
    return (torch.log(std) + 0.5 * math.log(2 * math.pi * math.e)).sum(-1)


def agent_embedding_std(emb: torch.Tensor) -> torch.Tensor:
    """Mean over the batch and the features of the population std over agents of embeddings (N, K, d): 0 when
    every UAV has the same embedding (the collapse of the paper's lesson 1)."""
    centred = emb - emb.mean(dim=1, keepdim=True)
    return centred.pow(2).mean(dim=1).sqrt().mean()


class CentralCritic(nn.Module):
    """V(s) on the flat global observation (N, D): Linear + ReLU layers, then one output (normalized units)."""

    def __init__(self, *, obs_dim: int, hidden: int, depth: int):
        super().__init__()
        layers: list[nn.Module] = []
        width = obs_dim
        for _ in range(depth):
            layers += [nn.Linear(width, hidden), nn.ReLU()]
            width = hidden
        self.net = nn.Sequential(*layers, nn.Linear(width, 1))

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        """(N,) values of flat observations (N, D)."""
        return self.net(obs).squeeze(-1)
