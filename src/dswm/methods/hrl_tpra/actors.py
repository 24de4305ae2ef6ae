"""The low level: K per-UAV resource actors and critics, each with its OWN weights, evaluated as one network.

:class:`StackedMLP` holds K MLPs as stacked parameters, weight (K, in, out) and bias (K, 1, out), and applies all of
them with one ``torch.baddbmm`` per layer; :class:`LoopMLP` is the same K networks as K separate ``nn.Module``s
called in a Python loop (the reference implementation and the benchmark's baseline, benchmarks/bench_hrl_tpra.py;
``LoopMLP.from_stacked`` copies the weights). The paper's implementation was kernel-launch bound in this loop.

Each actor maps its UAV's input (``features.low_inputs``) to the mean of a Gaussian over three outputs (fine dx,
fine dy, bandwidth logit); the log std is a learned (K, 3) parameter. Each critic maps the same input plus the
fleet-wide features to the team return (the reward is the fleet's).
"""
from __future__ import annotations

import math

import torch
from torch import nn

from dswm.methods.hrl_tpra.features import GLOBAL_FEATURES, N_ACTION


class StackedMLP(nn.Module):
    """K MLPs with separate weights applied together: (K, N, in) -> (K, N, out), ReLU between layers.

    Each agent's layer is initialized as ``nn.Linear`` would (uniform within 1 / sqrt(fan_in)); the last layer is
    scaled by ``out_gain`` (a small gain keeps the initial policy near its mean move).
    """

    def __init__(self, *, n: int, sizes: list[int], out_gain: float = 1.0):
        super().__init__()
        self.n, self.sizes = n, list(sizes)
        self.weights, self.biases = nn.ParameterList(), nn.ParameterList()
        for i, (fan_in, fan_out) in enumerate(zip(sizes[:-1], sizes[1:])):
            bound = 1.0 / math.sqrt(fan_in)
            gain = out_gain if i == len(sizes) - 2 else 1.0
            self.weights.append(nn.Parameter(torch.empty(n, fan_in, fan_out).uniform_(-bound, bound) * gain))
            self.biases.append(nn.Parameter(torch.empty(n, 1, fan_out).uniform_(-bound, bound) * gain))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(K, N, out) of inputs (K, N, in): agent k's rows through agent k's weights."""
        last = len(self.weights) - 1
        for i, (w, b) in enumerate(zip(self.weights, self.biases)):
            x = torch.baddbmm(b, x, w)
            if i < last:
                x = torch.relu(x)
        return x


class LoopMLP(nn.Module):
    """The same K networks as K separate modules, called one after the other (reference and benchmark)."""

    def __init__(self, *, n: int, sizes: list[int]):
        super().__init__()
        nets = []
        for _ in range(n):
            layers: list[nn.Module] = []
            for i, (fan_in, fan_out) in enumerate(zip(sizes[:-1], sizes[1:])):
                layers += [nn.Linear(fan_in, fan_out)] + ([nn.ReLU()] if i < len(sizes) - 2 else [])
            nets.append(nn.Sequential(*layers))
        self.nets = nn.ModuleList(nets)

    @classmethod
    def from_stacked(cls, stacked: StackedMLP) -> "LoopMLP":
        """A loop of modules holding copies of ``stacked``'s weights."""
        loop = cls(n=stacked.n, sizes=stacked.sizes)
        with torch.no_grad():
            for k, net in enumerate(loop.nets):
                linears = [m for m in net if isinstance(m, nn.Linear)]
                for lin, w, b in zip(linears, stacked.weights, stacked.biases, strict=True):
                    lin.weight.copy_(w[k].T)
                    lin.bias.copy_(b[k, 0])
        return loop

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(K, N, out) of inputs (K, N, in), agent by agent."""
        return torch.stack([net(x[k]) for k, net in enumerate(self.nets)])


class ResourceActors(nn.Module):
    """K resource actors (Gaussian policies) and K critics, stacked (see the module docstring).

    Args:
        n_uavs: K; in_dim: width of a UAV's input; hidden, depth: each MLP's hidden width and layers;
        log_std_init: initial log std of every output.
    """

    def __init__(self, *, n_uavs: int, in_dim: int, hidden: int, depth: int, log_std_init: float):
        super().__init__()
        self.actor = StackedMLP(n=n_uavs, sizes=[in_dim] + [hidden] * depth + [N_ACTION], out_gain=0.01)
        self.critic = StackedMLP(n=n_uavs, sizes=[in_dim + len(GLOBAL_FEATURES)] + [hidden] * depth + [1])
        self.log_std = nn.Parameter(torch.full((n_uavs, N_ACTION), float(log_std_init)))

    def actor_parameters(self) -> list[nn.Parameter]:
        return [*self.actor.parameters(), self.log_std]

    def mean(self, local: torch.Tensor) -> torch.Tensor:
        """(B, K, 3) Gaussian means of inputs (B, K, D)."""
        return self.actor(local.transpose(0, 1)).transpose(0, 1)

    def value(self, local: torch.Tensor, glob: torch.Tensor) -> torch.Tensor:
        """(B, K) each UAV's critic's value of inputs (B, K, D) and fleet-wide features (B, G)."""
        x = torch.cat([local, glob.unsqueeze(1).expand(-1, local.shape[1], -1)], dim=-1)
        return self.critic(x.transpose(0, 1)).squeeze(-1).transpose(0, 1)

    def log_prob(self, mean: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        """(B, K) log-density of raw actions (B, K, 3) under the Gaussians of ``mean`` (summed over outputs)."""
        std = self.log_std.exp()
        z = (action - mean) / std
        return (-0.5 * z.pow(2) - self.log_std - 0.5 * math.log(2 * math.pi)).sum(-1)

    def entropy(self) -> torch.Tensor:
        """(K,) entropy of each UAV's Gaussian."""
        return (self.log_std + 0.5 * math.log(2 * math.pi * math.e)).sum(-1)

    def sample(self, mean: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
        """Raw actions (B, K, 3) drawn from the Gaussians (unclipped; the action sent is clipped)."""
        noise = torch.randn(mean.shape, generator=generator).to(mean)  # drawn on the CPU: device-independent
        return mean + self.log_std.exp() * noise
