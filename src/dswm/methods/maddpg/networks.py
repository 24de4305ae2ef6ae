"""What each UAV sees, the shared actor and the centralized critic of MADDPG.

Observations are the environment's (``dswm.sim.core.build_observation``): demand (N, w+1, R, C), fleet (N, K, 7),
time (N, 2). Demand enters every network as :func:`scale_demand` = log1p(x), a fixed scaling: the tensors are
normalized by the training 99th percentile, so most values lie in [0, 1]; log1p keeps them there and compresses
the rare peaks. The functions below take maps already scaled.

* Local observation of UAV k (:func:`local_observation`), what its actor acts on: a (2 r + 1)^2 crop of the w+1
  log1p demand maps centred on its own cell, zero outside the area, plus one channel counting the OTHER active
  UAVs in each cell of the crop; its own fleet features (7); the time phase (2). Its index enters the actor as a
  learned embedding.
* Joint observation (:func:`joint_observation`), what the critic sees: the union of the agents' observations,
  i.e. the environment's whole observation (all log1p maps, every UAV's fleet features, the time phase).
"""
from __future__ import annotations

import torch
from torch import nn

N_ACTION = 3
"""(dx, dy, bw_logit) per UAV."""
N_FLEET = 7
"""Fleet features per UAV (``dswm.sim.core.FLEET_FEATURES``)."""


def local_dim(maps: int, radius: int) -> int:
    """Width of a local observation: ``maps`` (= w+1) demand channels and the occupancy channel over
    (2 r + 1)^2 cells, then its own fleet features and the time phase."""
    side = 2 * radius + 1
    return (maps + 1) * side * side + N_FLEET + 2


def joint_dim(maps: int, rows: int, cols: int, n_agents: int) -> int:
    """Width of the joint observation: ``maps`` (= w+1) maps of R x C cells, every UAV's fleet features, time."""
    return maps * rows * cols + N_FLEET * n_agents + 2


def scale_demand(demand: torch.Tensor) -> torch.Tensor:
    """The fixed scaling of demand values for every network: log1p(x)."""
    return torch.log1p(demand)


def cells_of(fleet: torch.Tensor, rows: int, cols: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(row, col) of each UAV's cell, (N, K) int64, from the fleet features x / W and y / H (row 0 south)."""
    col = torch.clamp((fleet[..., 0] * cols).floor().long(), 0, cols - 1)
    row = torch.clamp((fleet[..., 1] * rows).floor().long(), 0, rows - 1)
    return row, col


def local_observation(maps: torch.Tensor, fleet: torch.Tensor, time: torch.Tensor, radius: int) -> torch.Tensor:
    """The local observation of every UAV.

    Args:
        maps: (N, w+1, R, C) scaled demand maps (:func:`scale_demand`); fleet: (N, K, 7); time: (N, 2).
        radius: crop half-width r in cells.

    Returns:
        (N, K, local_dim(w+1, r)) float32: the crop (channels, rows, cols) flattened, then fleet_k, then time.
    """
    n, _, rows, cols = maps.shape
    k = fleet.shape[1]
    side = 2 * radius + 1
    row, col = cells_of(fleet, rows, cols)
    active = fleet[..., 3]
    # Occupancy: active UAVs per cell (N, R, C); each UAV later removes itself from the centre of its crop.
    occupancy = torch.zeros(n, rows * cols, dtype=maps.dtype, device=maps.device)
    occupancy.scatter_add_(1, row * cols + col, active.to(maps.dtype))
    channels = torch.cat([maps, occupancy.view(n, 1, rows, cols)], dim=1)  # (N, w+2, R, C)
    padded = nn.functional.pad(channels, (radius, radius, radius, radius)).permute(0, 2, 3, 1)  # (N, R+2r, C+2r, w+2)
    offs = torch.arange(side, device=maps.device)
    rr = (row.unsqueeze(-1) + offs).unsqueeze(-1)  # (N, K, S, 1) padded row of each crop row
    cc = (col.unsqueeze(-1) + offs).unsqueeze(-2)  # (N, K, 1, S)
    batch = torch.arange(n, device=maps.device).view(n, 1, 1, 1)
    crop = padded[batch, rr, cc]  # (N, K, S, S, w+2)
    crop[:, :, radius, radius, -1] -= active.to(crop.dtype)
    crop = crop.permute(0, 1, 4, 2, 3).reshape(n, k, -1)
    return torch.cat([crop, fleet, time.unsqueeze(1).expand(n, k, time.shape[-1])], dim=-1)


def joint_observation(maps: torch.Tensor, fleet: torch.Tensor, time: torch.Tensor) -> torch.Tensor:
    """(N, joint_dim) the critic's input: the scaled maps (N, w+1, R, C), all fleet features, time, flattened."""
    n = maps.shape[0]
    return torch.cat([maps.reshape(n, -1), fleet.reshape(n, -1), time], dim=-1)


class SharedActor(nn.Module):
    """One actor for every UAV: [local observation, index embedding] -> hidden features -> 3 pre-tanh outputs.

    Both stages are ``torchrl.modules.MultiAgentMLP`` with shared parameters and no centralization, applied
    over the agent axis; the body's last ReLU layer is the per-agent embedding whose spread across agents is
    monitored (a collapsed actor would give every UAV the same features).
    """

    def __init__(self, *, n_agents: int, obs_dim: int, embed: int, hidden: int, depth: int):
        super().__init__()
        self.n_agents = n_agents
        self.index = nn.Embedding(n_agents, embed)
        # torchrl is imported here, not with the module: reading MADDPG's settings (every workflow parse) needs none
        from torchrl.modules import MultiAgentMLP

        common = dict(n_agents=n_agents, centralised=False, share_params=True, activation_class=nn.ReLU)
        self.body = MultiAgentMLP(n_agent_inputs=obs_dim + embed, n_agent_outputs=hidden, depth=depth - 1,
                                  num_cells=hidden, activate_last_layer=True, **common)
        self.head = MultiAgentMLP(n_agent_inputs=hidden, n_agent_outputs=N_ACTION, depth=0, **common)

    def features(self, local: torch.Tensor) -> torch.Tensor:
        """(N, K, hidden) per-agent embeddings of local observations (N, K, obs_dim)."""
        idx = self.index.weight.unsqueeze(0).expand(local.shape[0], -1, -1)
        return self.body(torch.cat([local, idx], dim=-1))

    def forward(self, local: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Pre-tanh outputs (N, K, 3) and the features (N, K, hidden); the action is tanh of the first."""
        feats = self.features(local)
        return self.head(feats), feats


def agent_spread(features: torch.Tensor) -> torch.Tensor:
    """Mean over the batch and the feature axis of the population std over agents of (N, K, H) features."""
    centred = features - features.mean(dim=1, keepdim=True)
    return centred.pow(2).mean(dim=1).sqrt().mean()


class CentralCritic(nn.Module):
    """Q(x, a_1..a_K) on the joint observation x and the joint action (team reward: one Q for every agent).

    The first layer is split, h = W_x x + W_a a + b, so that Q with ONE agent's action replaced (the MADDPG
    actor objective, :meth:`substituted`) costs one small matrix product per agent instead of a full pass.
    """

    def __init__(self, *, obs_dim: int, n_agents: int, hidden: int, depth: int):
        super().__init__()
        self.n_agents = n_agents
        self.obs_in = nn.Linear(obs_dim, hidden)
        self.act_in = nn.Linear(n_agents * N_ACTION, hidden, bias=False)
        layers: list[nn.Module] = []
        for _ in range(depth - 1):
            layers += [nn.ReLU(), nn.Linear(hidden, hidden)]
        self.trunk = nn.Sequential(*layers, nn.ReLU(), nn.Linear(hidden, 1))

    def forward(self, x: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """(N,) Q of joint observations (N, D) and joint actions (N, K, 3)."""
        return self.trunk(self.obs_in(x) + self.act_in(action.flatten(1))).squeeze(-1)

    def substituted(self, x: torch.Tensor, action: torch.Tensor, new: torch.Tensor) -> torch.Tensor:
        """(N, K): entry (n, i) is Q(x_n, a_n with agent i's action replaced by new[n, i]).

        Args:
            x: (N, D) joint observations; action: (N, K, 3) replayed joint actions; new: (N, K, 3).
        """
        base = self.obs_in(x) + self.act_in(action.flatten(1))  # (N, H)
        weight = self.act_in.weight.view(-1, self.n_agents, N_ACTION)  # (H, K, 3)
        delta = torch.einsum("nka,hka->nkh", new - action, weight)  # (N, K, H)
        return self.trunk(base.unsqueeze(1) + delta).squeeze(-1)
