"""RSSM: KL value, balancing weights, gradient routing of the two KL terms, free bits, shapes."""
import torch
from torch.distributions import Normal, kl_divergence

from dswm.methods.dswm.rssm import RSSM, RSSMConfig, gaussian_kl


def _rssm(**kw) -> RSSM:
    torch.manual_seed(0)
    cfg = RSSMConfig(**{"deter": 12, "stoch": 5, "hidden": 16, "embed": 7, "min_std": 0.1, "free_bits": 0.1,
                         "kl_dyn": 0.8, "kl_rep": 0.2, **kw})
    return RSSM(cfg=cfg, action_dim=6)


def _step(rssm: RSSM):
    torch.manual_seed(1)
    b = 4
    prev = rssm.initial(b)
    prev = prev._replace(deter=torch.randn(b, 12), stoch=torch.randn(b, 5))
    return rssm.obs_step(prev, torch.randn(b, 6), torch.randn(b, 7))


def _grad_norms(rssm: RSSM, loss: torch.Tensor) -> dict[str, float]:
    rssm.zero_grad()
    loss.backward()
    out = {}
    for name in ("post_net", "prior_net"):
        out[name] = sum(float(p.grad.abs().sum()) for p in getattr(rssm, name).parameters()
                        if p.grad is not None)
    return out


def test_gaussian_kl_matches_closed_form():
    mq, sq = torch.tensor([0.3, -1.0]), torch.tensor([0.5, 2.0])
    mp, sp = torch.tensor([0.0, 1.0]), torch.tensor([1.0, 0.7])
    ref = kl_divergence(Normal(mq, sq), Normal(mp, sp))
    # hand value of the first dimension: 0.5 * (0.25 + 0.09 - 1 - ln 0.25) = 0.36314718...
    assert abs(float(gaussian_kl(mq, sq, mp, sp)[0]) - 0.3631471805599453) < 1e-6
    torch.testing.assert_close(gaussian_kl(mq, sq, mp, sp), ref)


def test_dyn_term_moves_only_prior_and_rep_term_only_posterior():
    rssm = _rssm(free_bits=0.0, kl_dyn=0.8, kl_rep=0.0)
    post, prior = _step(rssm)
    g = _grad_norms(rssm, rssm.kl_loss(post, prior)[0])
    assert g["prior_net"] > 0 and g["post_net"] == 0.0

    rssm = _rssm(free_bits=0.0, kl_dyn=0.0, kl_rep=0.2)
    post, prior = _step(rssm)
    g = _grad_norms(rssm, rssm.kl_loss(post, prior)[0])
    assert g["post_net"] > 0 and g["prior_net"] == 0.0


def test_balancing_weights_scale_each_side():
    # Full 0.8/0.2 loss: the prior head's gradient is 0.8 x the gradient of the plain KL, the posterior
    # head's is 0.2 x (the KL value itself is the same function on both sides).
    rssm = _rssm(free_bits=0.0)
    post, prior = _step(rssm)
    loss, _ = rssm.kl_loss(post, prior)
    rssm.zero_grad()
    loss.backward()
    g_bal = {n: [p.grad.clone() for p in getattr(rssm, n).parameters()] for n in ("prior_net", "post_net")}
    rssm2 = _rssm(free_bits=0.0)
    post2, prior2 = _step(rssm2)
    plain = gaussian_kl(post2.mean, post2.std, prior2.mean, prior2.std).sum(-1).mean()
    rssm2.zero_grad()
    plain.backward()
    for name, w in (("prior_net", 0.8), ("post_net", 0.2)):
        for gb, p in zip(g_bal[name], getattr(rssm2, name).parameters()):
            torch.testing.assert_close(gb, w * p.grad, rtol=1e-4, atol=1e-7)


def test_free_bits_floor_per_dimension():
    rssm = _rssm(free_bits=50.0)  # far above any per-dimension KL here
    post, prior = _step(rssm)
    loss, info = rssm.kl_loss(post, prior)
    assert abs(loss.item() - (0.8 + 0.2) * 50.0 * 5) < 1e-4
    g = _grad_norms(rssm, loss)
    assert g["prior_net"] == 0.0 and g["post_net"] == 0.0
    assert float(info["kl"]) < 50.0


def test_observe_shapes_and_prior_mean_is_deterministic():
    rssm = _rssm()
    t, b = 3, 2
    posts, priors = rssm.observe(torch.randn(t, b, 7), torch.randn(t, b, 6), rssm.initial(b))
    assert posts.deter.shape == (t, b, 12) and priors.stoch.shape == (t, b, 5)
    torch.testing.assert_close(posts.deter, priors.deter)  # posterior and prior share h_t
    s = rssm.initial(b)
    a = torch.randn(b, 6)
    torch.testing.assert_close(rssm.img_step(s, a, sample=False).stoch, rssm.img_step(s, a, sample=False).mean)
