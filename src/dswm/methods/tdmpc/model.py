"""TOLD, TD-MPC's task-oriented latent dynamics model (Hansen et al. 2022), for the UAV fleet.

* encoder h(o) -> z: the observation o_t = (x_{t-w..t}, fleet (K, 7), time (2,)) of every method;
* latent dynamics d(z, a) -> z', reward R(z, a), twin action-values Q1, Q2(z, a) and a policy pi(z) in [-1, 1]^A.
An action is the whole fleet's move flattened, A = 3K.

Fixed scaling of the demand (no statistic of the data): the encoder reads log(1 + x) of the normalized maps
(``dswm.sim.core`` serves maps divided by the training 99th percentile, so values are mostly in [0, ~3] and the
log keeps hotspots from dominating). The fleet enters twice: its features through an MLP, and a map of where the
active UAVs are (a Gaussian bump of one cell's width per UAV) as one more conv channel beside the demand, so the
convs see UAVs and demand on the same grid.
"""
from __future__ import annotations

import torch
from torch import nn

from dswm.sim.core import FLEET_FEATURES

ACTIVE_FEATURE = FLEET_FEATURES.index("active")


def mlp(inp: int, hidden: int, out: int) -> nn.Sequential:
    """Two ELU hidden layers."""
    return nn.Sequential(nn.Linear(inp, hidden), nn.ELU(), nn.Linear(hidden, hidden), nn.ELU(),
                         nn.Linear(hidden, out))


def q_head(inp: int, hidden: int) -> nn.Sequential:
    """TD-MPC's Q network: a LayerNorm and tanh after the first layer keep the input scale of z in check."""
    return nn.Sequential(nn.Linear(inp, hidden), nn.LayerNorm(hidden), nn.Tanh(), nn.Linear(hidden, hidden),
                         nn.ELU(), nn.Linear(hidden, 1))


def scale_demand(demand: torch.Tensor, out: torch.Tensor | None = None) -> torch.Tensor:
    """The encoder's fixed scaling of the normalized maps: log(1 + max(x, 0)), written into ``out`` when given."""
    return torch.log1p(demand.clamp_min(0.0), out=out)


def fleet_map(fleet: torch.Tensor, rows: int, cols: int) -> torch.Tensor:
    """Where the active UAVs are, on the grid: sum over active UAVs of exp(-d^2 / 2), d in cells.

    Args:
        fleet: (N, K, 7) fleet features (positions as fractions of the area's width and height).
    Returns:
        (N, rows, cols).
    """
    x = fleet[..., 0] * cols - 0.5                                        # (N, K) in column units
    y = fleet[..., 1] * rows - 0.5                                        # row 0 is the southern edge
    c = torch.arange(cols, dtype=fleet.dtype, device=fleet.device)
    r = torch.arange(rows, dtype=fleet.dtype, device=fleet.device)
    gx = bump(c - x.unsqueeze(-1))                                        # (N, K, C)
    gy = bump(r - y.unsqueeze(-1))                                        # (N, K, R)
    return torch.einsum("nk,nkr,nkc->nrc", fleet[..., ACTIVE_FEATURE], gy, gx)


LOG_SMALLEST_NORMAL = -87.33
"""Just above ln(2^-126) = -87.3365, the log of float32's (and bfloat16's) smallest normal number 1.175e-38."""


def bump(d: torch.Tensor) -> torch.Tensor:
    """exp(-d^2 / 2), with the values below exp(-87.33) = 1.18e-38 (|d| > 13.22, where exp gives a subnormal number
    or 0 beyond a hair's width) set to 0. Every other value is exp's own. Computing subnormal results takes the
    CPU's slow path: it made the fleet map ~3x slower, ~3% of a TD-MPC gradient step at the paper's sizes, for values
    no network can tell from 0 (Milan seed 0's demo TD-MPC job gives the same days and weights either way)."""
    a = -0.5 * d ** 2
    return torch.exp(a.clamp_min(LOG_SMALLEST_NORMAL)).masked_fill_(a < LOG_SMALLEST_NORMAL, 0.0)


def conv_dtype(x: torch.Tensor) -> torch.dtype:
    """The dtype the encoder's first conv reads: autocast's where it is on for ``x``'s device (its cast of a float32
    input rounds to nearest as writing into a buffer of that dtype does), else ``x``'s own."""
    kind = x.device.type
    return torch.get_autocast_dtype(kind) if torch.is_autocast_enabled(kind) else x.dtype


class Encoder(nn.Module):
    """h(o_t) -> z: two stride-2 convs over [log1p(demand window), fleet map], then an MLP with the fleet and time."""

    def __init__(self, *, window: int, rows: int, cols: int, n_uavs: int, channels: int, hidden: int, latent: int):
        super().__init__()
        self.rows, self.cols = rows, cols
        c = channels
        self.conv = nn.Sequential(nn.Conv2d(window + 1, c, 3, stride=2, padding=1), nn.ELU(),
                                  nn.Conv2d(c, 2 * c, 3, stride=2, padding=1), nn.ELU(), nn.Flatten())
        conv_out = 2 * c * ((rows + 3) // 4) * ((cols + 3) // 4)
        self.head = mlp(conv_out + n_uavs * len(FLEET_FEATURES) + 2, hidden, latent)

    def forward(self, demand: torch.Tensor, fleet: torch.Tensor, time: torch.Tensor, *,
                scaled: bool = False) -> torch.Tensor:
        """Args: demand (N, w+1, R, C) normalized maps (``scaled``: their :func:`scale_demand` already), fleet
        (N, K, 7), time (N, 2).  Returns: z (N, latent)."""
        return self.from_image(self.image(demand, fleet, scaled), fleet, time)

    def from_image(self, img: torch.Tensor, fleet: torch.Tensor, time: torch.Tensor) -> torch.Tensor:
        """z (N, latent) from the convs' input (N, w+2, R, C) (:meth:`image`), fleet (N, K, 7) and time (N, 2).

        A bfloat16 input is laid out channels-last before the convs: at these sizes oneDNN's bfloat16 convolutions
        run ~1.5x faster in that layout and give the same values; float32 keeps its layout (there the gain is small
        and the sums' order, hence the last bit, would change)."""
        if img.dtype == torch.bfloat16:
            img = img.contiguous(memory_format=torch.channels_last)
        return self.head(torch.cat([self.conv(img), fleet.flatten(1), time], -1))

    def image(self, demand: torch.Tensor, fleet: torch.Tensor, scaled: bool) -> torch.Tensor:
        """The convs' input [log1p(demand), fleet map] (..., w+2, R, C) of maps (..., w+1, R, C) and fleets
        (..., K, 7) of any leading shape, each written into its channels of one contiguous buffer: the values of
        their concatenation, without its copy, and maps given as a strided view (the replay's overlapping
        windows) are read in the same pass. Under autocast the buffer has autocast's dtype, so the conv does not
        cast a float32 copy of it again."""
        lead, m = demand.shape[:-3], demand.shape[-3]
        img = torch.empty((*lead, m + 1, self.rows, self.cols), dtype=conv_dtype(demand), device=demand.device)
        if scaled:
            img[..., :m, :, :] = demand
        else:   # into a bfloat16 buffer log1p still computes in float32 and rounds once, as a cast after it would
            scale_demand(demand, out=img[..., :m, :, :])
        flat = fleet.reshape(-1, *fleet.shape[-2:])
        img[..., m, :, :] = fleet_map(flat, self.rows, self.cols).view(*lead, self.rows, self.cols)
        return img


class TOLD(nn.Module):
    """The five TD-MPC components on one latent space (see the module docstring)."""

    def __init__(self, *, window: int, rows: int, cols: int, n_uavs: int, latent: int, hidden: int,
                 channels: int):
        """Args: window: w+1 maps per observation; rows, cols: the grid; n_uavs: K; latent, hidden, channels: sizes."""
        super().__init__()
        self.rows, self.cols, self.n_uavs = rows, cols, n_uavs
        self.latent, self.action_dim = latent, 3 * n_uavs
        za = latent + self.action_dim
        self.encoder = Encoder(window=window, rows=rows, cols=cols, n_uavs=n_uavs, channels=channels, hidden=hidden,
                               latent=latent)
        self.dynamics = mlp(za, hidden, latent)
        self.reward = mlp(za, hidden, 1)
        self.policy = mlp(latent, hidden, self.action_dim)
        self.q1, self.q2 = q_head(za, hidden), q_head(za, hidden)
        # TD-MPC initializes the last layers of the reward and the Q heads at zero: returns start at 0.
        for head in (self.reward, self.q1, self.q2):
            nn.init.zeros_(head[-1].weight)
            nn.init.zeros_(head[-1].bias)

    def encode(self, demand: torch.Tensor, fleet: torch.Tensor, time: torch.Tensor, *,
               scaled: bool = False) -> torch.Tensor:
        """h: observations with any leading shape (...) -> z (..., latent); ``scaled``: the maps are
        :func:`scale_demand` of the normalized ones (the replay's, transformed once per buffer)."""
        lead = fleet.shape[:-2]
        img = self.encoder.image(demand, fleet, scaled)
        z = self.encoder.from_image(img.view(-1, *img.shape[-3:]), fleet.reshape(-1, *fleet.shape[-2:]),
                                    time.reshape(-1, 2))
        return z.reshape(*lead, self.latent)

    def next(self, z: torch.Tensor, a: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """d and R: (..., latent), (..., A) -> next latent (..., latent) and predicted reward (...)."""
        za = torch.cat([z, a], -1)
        return self.dynamics(za), self.reward(za).squeeze(-1)

    def q(self, z: torch.Tensor, a: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Twin action-values Q1, Q2: (..., latent), (..., A) -> (...), (...)."""
        za = torch.cat([z, a], -1)
        return self.q1(za).squeeze(-1), self.q2(za).squeeze(-1)

    def pi(self, z: torch.Tensor, std: float = 0.0, generator: torch.Generator | None = None) -> torch.Tensor:
        """Policy: tanh(policy(z)), plus Gaussian noise of ``std`` (clipped to [-1, 1]) when std > 0. (..., A)."""
        a = torch.tanh(self.policy(z))
        if std > 0:
            a = (a + std * torch.randn(a.shape, generator=generator, device=a.device, dtype=a.dtype)).clamp(-1, 1)
        return a

    def model_parameters(self) -> list[nn.Parameter]:
        """Everything the TOLD loss trains: all but the policy."""
        skip = {id(p) for p in self.policy.parameters()}
        return [p for p in self.parameters() if id(p) not in skip]
