"""Latent predictive regularization: EMA arithmetic, variance margin value and its anti-collapse effect."""
import copy

import torch
from torch import nn

from dswm.methods.dswm.modules import ema_update, symexp, symlog, variance_margin


def test_ema_update_arithmetic():
    teacher, student = nn.Linear(2, 1), nn.Linear(2, 1)
    with torch.no_grad():
        for p in teacher.parameters():
            p.fill_(1.0)
        for p in student.parameters():
            p.fill_(3.0)
    ema_update(teacher, student, 0.9)
    assert torch.allclose(teacher.weight, torch.full((1, 2), 1.2))   # 0.9*1 + 0.1*3
    ema_update(teacher, student, 0.9)
    assert torch.allclose(teacher.bias, torch.tensor([1.38]))         # 0.9*1.2 + 0.1*3
    assert torch.allclose(student.weight, torch.full((1, 2), 3.0))    # student untouched


def test_variance_margin_value():
    h = torch.tensor([[0.0, 0.0], [2.0, 0.2]])  # per-dimension std (unbiased): sqrt(2), sqrt(0.02)
    eps = 1e-4
    expected = max(0.0, 0.5 - (2.0 + eps) ** 0.5) + max(0.0, 0.5 - (0.02 + eps) ** 0.5)
    assert abs(float(variance_margin(h, 0.5, eps)) - expected) < 1e-6


def test_symlog_roundtrip():
    x = torch.tensor([-3.0, 0.0, 0.5, 40.0])
    torch.testing.assert_close(symexp(symlog(x)), x)
    assert abs(float(symlog(torch.tensor(1.0))) - 0.6931471805599453) < 1e-6


def _toy(lam: float, margin: float = 0.5, steps: int = 300) -> torch.Tensor:
    """JEPA on data whose next step is independent noise: the predictable target is a constant, so the
    unregularized encoder drifts toward it (collapse); returns per-dimension std of the encoder output."""
    torch.manual_seed(0)
    f = nn.Sequential(nn.Linear(8, 16), nn.Tanh())
    g = nn.Linear(16, 16)
    teacher = copy.deepcopy(f).requires_grad_(False)
    opt = torch.optim.Adam([*f.parameters(), *g.parameters()], lr=1e-2)
    for _ in range(steps):
        x, x_next = torch.randn(256, 8), torch.randn(256, 8)
        h = f(x)
        loss = ((g(h) - teacher(x_next)) ** 2).sum(-1).mean() + lam * variance_margin(h, margin)
        opt.zero_grad()
        loss.backward()
        opt.step()
        ema_update(teacher, f, 0.9)
    with torch.no_grad():
        return f(torch.randn(4096, 8)).std(0)


def test_variance_margin_prevents_collapse():
    free = _toy(0.0)
    kept = _toy(1.0)
    assert float(free.mean()) < 0.5 * 0.5         # unregularized: collapsing below half the margin
    assert float(kept.min()) > 0.95 * 0.5         # every dimension kept near/above the margin


def test_demand_floor_and_head_layouts():
    from dswm.methods.dswm.modules import DemandEnsemble
    from dswm.methods.dswm.world_model import DEMAND_FLOOR, to_demand

    y = torch.tensor([-2.0, 0.0, 5e-5, 2e-4, 1.0])
    # symexp: [-, 0, 5.00013e-5 (< floor), 2.0002e-4, e - 1]; below the floor -> 0
    torch.testing.assert_close(to_demand(y), torch.tensor([0.0, 0.0, 0.0, 2.00020001e-4, 1.718281828]))
    assert DEMAND_FLOOR == 1e-4
    torch.manual_seed(0)
    ens = DemandEnsemble(feat_dim=6, n_heads=3, hidden=5, rank=2, n_cells=4)
    f = torch.randn(7, 6)
    torch.testing.assert_close(ens(f, heads_first=True), ens(f).transpose(0, 1))
