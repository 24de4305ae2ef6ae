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

from dswm.methods.matmul import MATMUL_DTYPES, linear, set_matmul_dtype

N_ACTION = 3
"""(dx, dy, bw_logit) per UAV."""
HEAD_INIT = 3e-3
"""The actor head's last layer starts uniform in +-HEAD_INIT (weights and bias), as DDPG's (Lillicrap et al. 2016,
section 7), so that the untrained policy's outputs are near zero: an active UAV stays about where it is instead of the
fleet drifting one way every slot."""
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
        (N, K, local_dim(w+1, r)) in the dtype of ``maps``: the crop (rows, cols, channels) flattened, then fleet_k,
        then time
        (channels last, so that each crop row is one contiguous copy; :class:`SharedActor` orders its weight so).
    """
    n, m, rows, cols = maps.shape
    k = fleet.shape[1]
    side, ch, pr, pc = 2 * radius + 1, m + 1, rows + 2 * radius, cols + 2 * radius
    row, col = cells_of(fleet, rows, cols)
    active = fleet[..., 3].to(maps.dtype)
    # Channels-last maps padded with r zero cells: the w+1 maps, then the active UAVs per cell (occupancy)
    padded = torch.empty(n, pr, pc, ch, dtype=maps.dtype, device=maps.device)
    for border in (padded[:, :radius], padded[:, radius + rows:], padded[:, radius:radius + rows, :radius],
                   padded[:, radius:radius + rows, radius + cols:]):
        border.zero_()
    padded[:, radius:radius + rows, radius:radius + cols, :m] = maps.permute(0, 2, 3, 1)
    occupancy = torch.zeros(n, pr * pc, dtype=maps.dtype, device=maps.device)
    occupancy.scatter_add_(1, (row + radius) * pc + col + radius, active)
    padded[..., m] = occupancy.view(n, pr, pc)
    # Every row of every S x S window is S cells x (w+2) channels contiguous: viewed as the overlapping spans that
    # start at each cell, the window of a UAV whose own cell is (row, col) is the S spans starting at padded cells
    # (row + i, col), i < S (its top-left corner is the UAV's cell), gathered whole by index_select
    spans = padded.view(-1).as_strided((n * pr * pc - side + 1, side * ch), (ch, 1))
    start = (torch.arange(n, device=maps.device).view(n, 1, 1) * (pr * pc)
             + (row.unsqueeze(-1) + torch.arange(side, device=maps.device)) * pc + col.unsqueeze(-1))
    crop = spans.index_select(0, start.view(-1)).view(n, k, -1)  # (N, K, S S (w+2))
    crop[..., (radius * side + radius) * ch + m] -= active  # each UAV removes itself from its own cell's count
    return torch.cat([crop, fleet.to(crop.dtype), time.to(crop.dtype).unsqueeze(1).expand(n, k, time.shape[-1])],
                     dim=-1)


def joint_observation(maps: torch.Tensor, fleet: torch.Tensor, time: torch.Tensor) -> torch.Tensor:
    """(N, joint_dim) the critic's input: the scaled maps (N, w+1, R, C), all fleet features, time, flattened, in
    the dtype of ``maps``."""
    n = maps.shape[0]
    return torch.cat([maps.reshape(n, -1), fleet.reshape(n, -1).to(maps.dtype), time.to(maps.dtype)], dim=-1)


class SharedActor(nn.Module):
    """One actor for every UAV: [local observation, index embedding] -> hidden features -> 3 pre-tanh outputs.

    Both stages are ``torchrl.modules.MultiAgentMLP`` with shared parameters and no centralization (they hold the
    parameters and the state dict; :meth:`features` runs their layers over the agent axis); the body's last ReLU
    layer is the per-agent embedding whose spread across agents is monitored (a collapsed actor would give every
    UAV the same features). The head starts near zero (:data:`HEAD_INIT`): the untrained actor barely moves.
    """

    def __init__(self, *, n_agents: int, obs_dim: int, embed: int, hidden: int, depth: int, crop: tuple[int, int],
                 matmul_dtype: str = "float32"):
        super().__init__()
        self.n_agents, self.depth, self.dtype = n_agents, depth, MATMUL_DTYPES[matmul_dtype]
        self.crop = crop
        self.index = nn.Embedding(n_agents, embed)
        # torchrl is imported here, not with the module: reading MADDPG's settings (every workflow parse) needs none
        from torchrl.modules import MultiAgentMLP

        common = dict(n_agents=n_agents, centralised=False, share_params=True, activation_class=nn.ReLU)
        self.body = MultiAgentMLP(n_agent_inputs=obs_dim + embed, n_agent_outputs=hidden, depth=depth - 1,
                                  num_cells=hidden, activate_last_layer=True, **common)
        self.head = MultiAgentMLP(n_agent_inputs=hidden, n_agent_outputs=N_ACTION, depth=0, **common)
        with torch.no_grad():  # near-zero initial actions (HEAD_INIT)
            for name in ("weight", "bias"):
                self.head.params["0", name].uniform_(-HEAD_INIT, HEAD_INIT)

    def features(self, local: torch.Tensor) -> torch.Tensor:
        """(N, K, hidden) per-agent embeddings of local observations (N, K, obs_dim).

        The body's layers run on its (shared) parameters directly: its first layer takes [local, index embedding]
        as W_o local + W_e e_k + b, so the embedding's part is computed once per agent, not once per row. Its crop
        columns are stored in (channels, rows, cols) order and permuted to the local view's channels-last order
        (``crop`` = (channels, side)).
        """
        p = self.body.params
        weight, d = p["0", "weight"], local.shape[-1]
        channels, side = self.crop
        width = channels * side * side
        # The weight's crop columns are kept in (channels, rows, cols) order; the local crop is channels last
        crop = weight[:, :width].unflatten(1, (channels, side, side)).permute(0, 2, 3, 1).flatten(1)
        local_weight = torch.cat([crop, weight[:, width:d]], dim=1)
        per_agent = linear(self.index.weight, weight[:, d:], p["0", "bias"], self.dtype)  # (K, hidden)
        h = torch.relu(linear(local, local_weight, None, self.dtype) + per_agent)
        for i in range(2, 2 * self.depth, 2):
            h = torch.relu(linear(h, p[str(i), "weight"], p[str(i), "bias"], self.dtype))
        return h

    def forward(self, local: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Pre-tanh outputs (N, K, 3) and the features (N, K, hidden); the action is tanh of the first."""
        feats = self.features(local)
        return linear(feats, self.head.params["0", "weight"], self.head.params["0", "bias"], self.dtype), feats


def agent_spread(features: torch.Tensor) -> torch.Tensor:
    """Mean over the batch and the feature axis of the population std over agents of (N, K, H) features."""
    centred = features - features.mean(dim=1, keepdim=True)
    return centred.pow(2).mean(dim=1).sqrt().mean()


class CentralCritic(nn.Module):
    """Q(x, a_1..a_K) on the joint observation x and the joint action (team reward: one Q for every agent).

    The first layer is split, h = W_x x + W_a a + b, so that Q with ONE agent's action replaced (the MADDPG
    actor objective, :meth:`substituted`) costs one small matrix product per agent instead of a full pass.
    """

    def __init__(self, *, obs_dim: int, n_agents: int, hidden: int, depth: int, matmul_dtype: str = "float32"):
        super().__init__()
        self.n_agents = n_agents
        self.obs_in = nn.Linear(obs_dim, hidden)
        self.act_in = nn.Linear(n_agents * N_ACTION, hidden, bias=False)
        layers: list[nn.Module] = []
        for _ in range(depth - 1):
            layers += [nn.ReLU(), nn.Linear(hidden, hidden)]
        self.trunk = nn.Sequential(*layers, nn.ReLU(), nn.Linear(hidden, 1))
        set_matmul_dtype(self, matmul_dtype)

    def forward(self, x: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """(N,) Q of joint observations (N, D) and joint actions (N, K, 3)."""
        return self.trunk(self.obs_in(x) + self.act_in(action.flatten(1))).squeeze(-1)

    def substituted(self, x: torch.Tensor, action: torch.Tensor, new: torch.Tensor) -> torch.Tensor:
        """(N, K): entry (n, i) is Q(x_n, a_n with agent i's action replaced by new[n, i]).

        Args:
            x: (N, D) joint observations; action: (N, K, 3) replayed joint actions; new: (N, K, 3).
        """
        base = self.obs_in(x) + self.act_in(action.flatten(1))  # (N, H)
        n, k, _ = action.shape
        weight = self.act_in.weight.view(-1, self.n_agents, N_ACTION).permute(2, 1, 0).contiguous()  # (3, K, H)
        change = new - action  # (N, K, 3)
        h = base.unsqueeze(1) + change[..., 0, None] * weight[0]  # (N, K, H), contiguous
        for a in range(1, N_ACTION):
            h = h + change[..., a, None] * weight[a]
        return self.trunk(h.reshape(n * k, -1)).view(n, k)
