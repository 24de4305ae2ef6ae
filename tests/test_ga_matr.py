"""GA-MATR: UAV and context tokens, the attention mask, GAE at a day's end, HAPPO's sequential per-agent update
(order and weights), the fairness term, training on small synthetic days (value loss, cross-agent embedding
spread, checkpoint resumption, recorded days, seeds) and acting within bounds."""
import dataclasses
import math

import numpy as np
import pytest
import torch

from dswm.config import ConfigError
from dswm.methods.ga_matr import GAMATRController, GAMATRSettings
from dswm.methods.ga_matr.happo import Learner, Rollout, gae, happo_surrogate
from dswm.methods.ga_matr.networks import (GraphAttentionPolicy, PolicyInputs, agent_embedding_std, attention_mask,
                                           context_tokens, local_crops, log_prob, policy_inputs)
from dswm.methods.ga_matr.training import Trainer, load_cv
from dswm.methods.trained import day_schedule
from learner_checks import (DAY_IDS, check_actions_bounded_and_moves_within_dmax, check_same_seed_same_actions,
                            check_save_load, check_trains_on_training_days_and_evaluates_batched_as_alone)
from learner_checks import core, scenario3  # noqa: F401 (fixtures)

SMALL = GAMATRSettings(crop_radius=1, context_side=2, d_model=16, heads=2, layers=2, ffn_hidden=32, critic_hidden=32,
                       critic_depth=2, actor_lr=1e-3, critic_lr=1e-3, gamma=0.9, gae_lambda=0.95, clip_eps=0.2,
                       epochs=2, critic_epochs=20, minibatches=2, entropy_coef=0.0, init_std=0.5, max_grad_norm=1.0,
                       fairness_weight=0.1, matmul_dtype="float32", n_envs=2, transitions=6 * 286, log_points=6,
                       checkpoint_every=2)
QUICK = dataclasses.replace(SMALL, transitions=286, critic_epochs=2)  # one round of two days


@pytest.fixture(scope="module")
def fitted(core, tmp_path_factory):
    """SMALL trained on the core: (controller, manifest)."""
    ctrl = GAMATRController(name="ga_matr", seed=0, options=SMALL)
    manifest = ctrl.fit(core, run_dir=tmp_path_factory.mktemp("ga_matr_run"))
    return ctrl, manifest



def toy_policy(n_agents=3, seed=0):
    torch.manual_seed(seed)
    return GraphAttentionPolicy(n_agents=n_agents, uav_in=5, context_in=4, d_model=8, heads=2, layers=2,
                                ffn_hidden=16, init_std=0.5)


def toy_inputs(n, available, seed=0):
    g = torch.Generator().manual_seed(seed)
    return PolicyInputs(uav=torch.randn(n, 3, 5, generator=g), context=torch.randn(n, 4, 4, generator=g),
                        available=torch.as_tensor(available).expand(n, 3).clone())


# ----------------------------------------------------------------------------------- settings and inputs

@pytest.mark.parametrize("key,value", [("gamma", 1.0), ("clip_eps", 0.0), ("heads", 3), ("crop_radius", -1),
                                       ("fairness_weight", -0.1), ("epochs", 0), ("gae_lambda", 1.5)])
def test_settings_name_the_bad_key(key, value):
    with pytest.raises(ConfigError, match=f"methods.ga_matr.{key}"):
        dataclasses.replace(SMALL, **{key: value})


def test_transitions_must_be_whole_rounds(core, tmp_path):
    ctrl = GAMATRController(name="ga_matr", seed=0, options=dataclasses.replace(SMALL, transitions=143))
    with pytest.raises(ConfigError, match="methods.ga_matr.transitions.*multiple of 286"):
        ctrl.fit(core, run_dir=tmp_path)


def test_local_crops_are_centred_on_each_uav_and_zero_outside():
    rows, cols = 4, 5
    maps = torch.arange(2 * rows * cols, dtype=torch.float32).reshape(1, 2, rows, cols)  # values = flat index
    fleet = torch.zeros(1, 2, 7)
    fleet[0, :, 0] = torch.tensor([0.5, 2.5]) / cols  # UAV 0 in cell (row 0, col 0), UAV 1 in (row 3, col 2)
    fleet[0, :, 1] = torch.tensor([0.5, 3.5]) / rows
    crop = local_crops(maps, fleet, 1).reshape(2, 2, 3, 3)  # (agent, channel, row, col)
    assert crop[0, 0].tolist() == [[0, 0, 0], [0, 0, 1], [0, 5, 6]]
    assert crop[0, 1].tolist() == [[0, 0, 0], [0, 20, 21], [0, 25, 26]]
    assert crop[1, 0].tolist() == [[11, 12, 13], [16, 17, 18], [0, 0, 0]]


def test_context_tokens_pool_blocks_and_give_their_centres():
    maps = torch.arange(16, dtype=torch.float32).reshape(1, 1, 4, 4)
    tok = context_tokens(maps, 2)
    assert tok.shape == (1, 4, 4)
    # block (row 0, col 0) holds 0, 1, 4, 5; block (row 1, col 1) holds 10, 11, 14, 15
    assert tok[0, 0].tolist() == [2.5, 5.0, 0.25, 0.25]
    assert tok[0, 3].tolist() == [12.5, 15.0, 0.75, 0.75]
    assert tok[0, 1, 2:].tolist() == [0.75, 0.25]  # x then y


def test_policy_inputs_log1p_the_maps_and_mark_available_uavs():
    demand = torch.full((1, 7, 4, 4), math.e - 1.0)
    fleet = torch.zeros(1, 3, 7)
    fleet[0, :, 3] = torch.tensor([1.0, 0.0, 1.0])  # UAV 1 not active
    x = policy_inputs(demand, fleet, torch.tensor([[0.5, -0.5]]), radius=0, side=2)
    assert x.available.tolist() == [[True, False, True]]
    torch.testing.assert_close(x.uav[0, :, :7], torch.ones(3, 7))
    torch.testing.assert_close(x.uav[0, 1, 7:14], fleet[0, 1])
    assert x.uav[0, 2, -2:].tolist() == [0.5, -0.5]


# ----------------------------------------------------------------------------------- attention mask

def test_attention_mask_allows_available_uavs_and_oneself():
    mask = attention_mask(torch.tensor([[True, True, False]]))
    assert mask[0].tolist() == [[True, True, False], [True, True, False], [True, True, True]]


def test_a_masked_uav_receives_no_attention_and_changes_nothing_for_the_others():
    policy = toy_policy()
    x = toy_inputs(5, [True, True, False])
    with torch.no_grad():
        emb, weights = policy.embed(x, return_weights=True)
        for w in weights:  # every block: (N, heads, K, K)
            assert float(w["self"][:, :, :2, 2].abs().max()) == 0.0  # UAVs 0 and 1 pay UAV 2 nothing
            assert float(w["self"][:, :, :2, :2].min()) > 0.0
            torch.testing.assert_close(w["self"].sum(-1), torch.ones(5, 2, 3))
            assert float(w["self"][:, :, 2].min()) > 0.0  # UAV 2 itself attends to the available UAVs and itself
        changed = x._replace(uav=x.uav.clone())
        changed.uav[:, 2] += 3.0
        emb2 = policy.embed(changed)
        mean, _, _ = policy(x)
        mean2, _, _ = policy(changed)
    assert torch.equal(emb2[:, :2], emb[:, :2]) and torch.equal(mean2[:, :2], mean[:, :2])
    assert not torch.allclose(emb2[:, 2], emb[:, 2])
    # the same change of an AVAILABLE UAV 2 does reach the others
    live = x._replace(available=torch.ones(5, 3, dtype=torch.bool))
    with torch.no_grad():
        moved = policy.embed(live._replace(uav=changed.uav))
        assert not torch.allclose(moved[:, :2], policy.embed(live)[:, :2])


def test_bfloat16_products_keep_the_float32_stream_the_mask_and_every_gradient():
    policy = toy_policy()
    low = GraphAttentionPolicy(n_agents=3, uav_in=5, context_in=4, d_model=8, heads=2, layers=2, ffn_hidden=16,
                               init_std=0.5, matmul_dtype="bfloat16")
    low.load_state_dict(policy.state_dict())
    x = toy_inputs(64, [True, True, False])
    emb, _ = policy.embed(x, return_weights=True)
    emb_low, weights = low.embed(x, return_weights=True)
    assert emb_low.dtype == torch.float32 and low(x)[0].dtype == torch.float32
    gap = float((emb_low - emb).detach().abs().max())
    assert 0.0 < gap < 0.1  # the products rounded to 8 significant bits, the layer-normed embedding O(1)
    for w in weights:  # softmax in float32: rows sum to 1 and an unavailable UAV gets exactly 0
        assert w["self"].dtype == torch.float32 and float(w["self"][:, :, :2, 2].abs().max()) == 0.0
        torch.testing.assert_close(w["self"].sum(-1), torch.ones(64, 2, 3))
    changed = x._replace(uav=x.uav.clone())
    changed.uav[:, 2] += 3.0
    assert torch.equal(low.embed(changed)[:, :2], emb_low[:, :2])
    grads = []
    for net in (policy, low):
        net.zero_grad()
        mean, std, _ = net(x)
        (mean.pow(2).sum() + std.sum()).backward()
        grads.append({k: p.grad for k, p in net.named_parameters()})
    for name, grad in grads[1].items():
        assert grad.dtype == torch.float32, name
        torch.testing.assert_close(grad, grads[0][name], rtol=0.1, atol=0.02 * float(grads[0][name].abs().max()))


def test_agent_embedding_std_is_zero_for_identical_agents():
    assert float(agent_embedding_std(torch.randn(4, 1, 6).expand(4, 3, 6))) == pytest.approx(0.0, abs=1e-7)
    pair = torch.tensor([[[0.0, 2.0], [2.0, 0.0]]])
    assert float(agent_embedding_std(pair)) == pytest.approx(1.0)


def test_the_index_embedding_keeps_identical_uavs_apart():
    """Lesson 1: UAVs with identical inputs get distinct embeddings through their learned index embedding alone."""
    policy = toy_policy()
    x = toy_inputs(4, [True, True, True])
    same = x._replace(uav=x.uav[:, :1].expand(4, 3, 5).contiguous())
    with torch.no_grad():
        assert float(agent_embedding_std(policy.embed(same))) > 0.1
        policy.index.weight.zero_()
        assert float(agent_embedding_std(policy.embed(same))) == pytest.approx(0.0, abs=1e-6)


def test_log_prob_is_the_gaussian_density_of_the_unclipped_action():
    mean, std = torch.rand(4, 3, 3) * 2 - 1, torch.rand(3, 3) + 0.1
    action = torch.randn(4, 3, 3) * 2
    want = torch.distributions.Normal(mean, std.expand(4, 3, 3)).log_prob(action).sum(-1)
    torch.testing.assert_close(log_prob(mean, std, action), want)


# ----------------------------------------------------------------------------------- GAE and HAPPO

def test_gae_bootstraps_at_truncation_and_stops_at_termination():
    rewards = torch.tensor([[1.0, 1.0], [0.5, 0.5]])  # (T=2, E=2)
    values = torch.tensor([[0.2, 0.2], [0.4, 0.4]])
    last = torch.tensor([3.0, 3.0])
    terminated = torch.tensor([[False, False], [False, True]])  # env 0 truncated at the end, env 1 terminated
    adv, ret = gae(rewards, values, last, terminated, gamma=0.9, lam=0.5)
    d1 = torch.tensor([0.5 + 0.9 * 3.0 - 0.4, 0.5 - 0.4])
    d0 = 1.0 + 0.9 * 0.4 - 0.2
    torch.testing.assert_close(adv[1], d1)
    torch.testing.assert_close(adv[0], d0 + 0.9 * 0.5 * d1)
    torch.testing.assert_close(ret, adv + values)
    assert float(ret[1, 0]) == pytest.approx(0.5 + 0.9 * 3.0)  # r + gamma V(o_T) at the day's end


def test_happo_surrogate_is_clipped_and_weighted_by_the_factor():
    ratio = torch.tensor([1.5, 0.5, 1.5, 1.0])
    factor = torch.tensor([2.0, 1.0, 1.0, 3.0])
    adv = torch.tensor([1.0, -1.0, -1.0, 1.0])
    live = torch.tensor([True, True, True, False])
    got = happo_surrogate(ratio, factor, adv, 0.2, live)
    want = (min(1.5 * 2.0, 1.2 * 2.0) + min(-0.5, -0.8) + min(-1.5, -1.2)) / 3
    assert float(got) == pytest.approx(want, abs=1e-6)


def test_sequential_update_applies_the_seeded_order_and_weights_by_earlier_ratios():
    """3 UAVs: the permutation drawn from the generator is the order applied, and agent m's surrogate is weighted
    by the product of the ratios of the agents updated before it (each taken right after its own update)."""
    settings = dataclasses.replace(SMALL, d_model=8, ffn_hidden=16, epochs=3, minibatches=2, critic_epochs=1,
                                   actor_lr=3e-2)
    torch.manual_seed(0)
    learner = Learner(settings=settings, n_agents=3, uav_in=5, context_in=4, obs_dim=6)
    n = 64
    avail = torch.ones(n, 3, dtype=torch.bool)
    avail[::4, 1] = False  # UAV 1 is charging in a quarter of the samples
    x = toy_inputs(n, [True, True, True], seed=1)._replace(available=avail)
    action, old_logp = learner.sample(x, torch.Generator().manual_seed(2))
    batch = Rollout(inputs=x, critic_obs=torch.randn(n, 6), action=action, old_logp=old_logp,
                    advantage=torch.randn(n, generator=torch.Generator().manual_seed(3)), returns=torch.randn(n))
    trace = []
    out = learner.update(batch, torch.Generator().manual_seed(7), trace)
    order = torch.randperm(3, generator=torch.Generator().manual_seed(7)).tolist()
    assert out["order"] == order == [t["agent"] for t in trace]
    assert sorted(order) == [0, 1, 2]
    probe = toy_policy()
    probe.load_state_dict(learner.policy.state_dict())
    product = torch.ones(n)
    for step in trace:
        m = step["agent"]
        torch.testing.assert_close(step["factor"], product)  # the weight of agent m's surrogate
        probe.load_state_dict(step["policy"])  # the policy right after agent m's own update
        with torch.no_grad():
            mean, std, _ = probe(x)
            ratio = torch.exp(log_prob(mean, std, action)[:, m] - old_logp[:, m])
        ratio = torch.where(avail[:, m], ratio, torch.ones_like(ratio))
        torch.testing.assert_close(step["ratio"], ratio)
        product = product * ratio
    assert float((trace[2]["factor"] - 1).abs().max()) > 1e-2  # the weights are not trivially 1
    assert learner.steps == 3 * 3 * 2 + 1 * 2


def test_load_cv_counts_available_uavs_only():
    load = np.array([[1.0, 3.0, 0.0], [2.0, 2.0, 2.0], [5.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    avail = np.array([[True, True, False], [True, True, True], [True, False, False], [True, True, True]])
    np.testing.assert_allclose(load_cv(load, avail), [0.5, 0.0, 0.0, 0.0])


def test_learner_reward_is_eq7_minus_the_fairness_term(core):
    for weight in (0.0, 0.5):
        trainer = Trainer(core=core, settings=dataclasses.replace(QUICK, fairness_weight=weight), seed=0)
        rollout, stats = trainer.collect(np.array([0, 3]))
        assert stats["charts/load_cv"] > 0.05
        want = stats["charts/episode_return"] - weight * 143 * stats["charts/load_cv"]
        assert stats["charts/learner_return"] == pytest.approx(want, rel=1e-5)
        assert rollout.action.shape == (286, 3, 3) and rollout.returns.shape == (286,)


# ----------------------------------------------------------------------------------- training

def test_training_lowers_the_value_loss(fitted):
    ctrl, manifest = fitted
    value = manifest["history"]["losses/value"]
    assert manifest["steps"] >= 300
    assert value[-1] < 0.6 * value[0], value


def test_cross_agent_embedding_std_stays_above_a_floor(fitted, core):
    ctrl, manifest = fitted
    logged = manifest["history"]["diag/agent_embedding_std"]
    assert all(np.isfinite(logged)) and min(logged) > 0.1
    obs = core.reset([0, 1, 2, 3])
    x = policy_inputs(*(torch.as_tensor(obs[k]) for k in ("demand", "fleet", "time")), radius=1, side=2)
    with torch.no_grad():
        assert float(agent_embedding_std(ctrl.learner.policy.embed(x))) > 0.1


def test_manifest_records_exactly_the_training_days_used(fitted, core):
    ctrl, manifest = fitted
    schedule = day_schedule(core.n_days, 12, 0)
    assert manifest["days"] == [int(DAY_IDS[d]) for d in schedule]
    assert set(manifest["days"]) <= set(DAY_IDS.tolist())
    assert manifest["day_labels"] == [core.day_labels[d] for d in schedule]
    assert manifest["transitions_per_day_episode"] == 143
    assert manifest["n_transitions"] == 143 * len(manifest["days"]) == SMALL.transitions
    assert manifest["read_test_data"] is False
    history = manifest["history"]
    assert history["step"] == [286 * r for r in range(1, 7)] and all(len(v) == 6 for v in history.values())


def test_checkpoint_resumes_to_an_identical_next_round(core, tmp_path):
    settings = dataclasses.replace(QUICK, transitions=2 * 286)
    a = Trainer(core=core, settings=settings, seed=4)
    a.run_round()
    a.save(tmp_path / "ckpt.pt", {"run": 1})
    want = a.run_round()
    b = Trainer(core=core, settings=settings, seed=4)
    torch.manual_seed(123)  # the global RNG moves on: the checkpoint must bring everything back
    b.restore(torch.load(tmp_path / "ckpt.pt", weights_only=False))
    got = b.run_round()
    assert got == want  # days, returns and every update metric, exactly
    for p, q in zip(a.learner.policy.parameters(), b.learner.policy.parameters(), strict=True):
        assert torch.equal(p, q)
    assert a.history == b.history and a.days_used == b.days_used


def test_fit_continues_a_finished_run_from_its_checkpoint(core, tmp_path):
    first = GAMATRController(name="ga_matr", seed=1, options=QUICK).fit(core, run_dir=tmp_path)
    second = GAMATRController(name="ga_matr", seed=1, options=QUICK).fit(core, run_dir=tmp_path)
    assert second["days"] == first["days"] and second["steps"] == first["steps"] == 3 * 2 * 2 + 2 * 2
    assert second["history"] == first["history"]


# ----------------------------------------------------------------------------------- acting

def make(seed, options):
    return GAMATRController(name="ga_matr", seed=seed, options=options)


def test_actions_are_bounded_and_moves_stay_within_dmax(fitted, core):
    moved = check_actions_bounded_and_moves_within_dmax(fitted[0], core)
    assert moved > 1.0  # the policy does move the fleet


def test_same_seed_same_actions(core, tmp_path):
    check_same_seed_same_actions(make, QUICK, core, tmp_path)


def test_save_load_round_trip_and_checks(fitted, core, tmp_path):
    check_save_load(fitted[0], make, SMALL, dataclasses.replace(SMALL, d_model=8), core, tmp_path)


def test_trains_on_the_training_days_of_a_tensor_and_evaluates_batched_as_alone(scenario3, tmp_path):
    options = dataclasses.replace(QUICK, n_envs=3, transitions=429)
    check_trains_on_training_days_and_evaluates_batched_as_alone(make, options, scenario3, tmp_path)
