"""TD-MPC: settings, rewards of the replay, TD targets at truncation, losses that fall, exact resumes, MPPI on toy
problems, and the controller on small synthetic days (actions, D_max, the manifest's days, seeds)."""
import copy
import dataclasses

import numpy as np
import pytest
import torch

from dswm.config import ConfigError
from dswm.methods.base import DayContext
from dswm.methods.collect import collect
from dswm.methods.search import SearchSettings
from dswm.methods.tdmpc import learner as learner_mod
from dswm.methods.tdmpc import model as model_mod
from dswm.methods.tdmpc.agent import TDMPCController, project, round_bounds
from dswm.methods.tdmpc.diagnose import one_step_rewards, rank_correlation, reward_ranking
from dswm.methods.tdmpc.learner import Learner
from dswm.methods.tdmpc.planner import MPPIConfig, mppi
from dswm.methods.tdmpc.replay import TransitionReplay, episode_rewards
from dswm.methods.tdmpc.settings import PreCollect, TDMPCSettings, resolve
from dswm.sim.core import FleetCore, Grid, initial_positions
from dswm.sim.env import synthetic_demand

GRID = Grid(rows=6, cols=6, cell_m=235.0)
SLOTS = 40            # a short day keeps collection fast; every rule is the same as with 144 slots
DAY_IDS = np.array([4, 7, 9])   # tensor day of each core day (not 0..2, so a mix-up shows)
CHEAP = SearchSettings(sweeps=1, lattice=5, refine=0, bw_logits=())
PRE = PreCollect(transitions=2 * (SLOTS - 1), collect_policy="lloyd", collect_parallel=2, explore_std=0.3,
                 bw_explore_std=0.5, collect_search=CHEAP)
BASE = dict(latent=16, hidden=32, enc_channels=4, horizon=3, n_samples=32, policy_share=0.1, n_elites=4,
            iterations=2, temperature=0.5, momentum=0.1, min_std=0.05, max_std=2.0, gamma=0.95, rho=0.5, tau=0.01,
            consistency_coef=2.0, reward_coef=0.5, value_coef=0.1, lr=1e-3, pi_lr=1e-3, grad_clip=10.0, batch=16,
            steps=30, seed_steps=10, episodes=2, parallel=1, explore="mppi", explore_std=0.3, log_points=10,
            checkpoint_every=7, matmul_dtype="float32", precollect=PRE)


def settings(**kw) -> TDMPCSettings:
    return TDMPCSettings(**{**BASE, **kw})


@pytest.fixture(scope="module")
def scn(scenario):
    return dataclasses.replace(scenario, n_uavs=3, slots_per_day=SLOTS, demand_intensity=20.0)


def make_core(scn) -> FleetCore:
    demand = 3.0 * synthetic_demand(days=3, rows=GRID.rows, cols=GRID.cols, slots=SLOTS, seed=1) + 0.05
    init = initial_positions(demand.mean(axis=(0, 1)), GRID, scn.n_uavs, 0)
    core = FleetCore(demand=demand, grid=GRID, scenario=scn, init_pos=init, dataset="toy",
                     day_labels=["2020-01-04", "2020-01-07", "2020-01-09"])
    core.day_ids = DAY_IDS
    return core


def contexts(core, rows):
    return [DayContext(dataset="toy", day=int(DAY_IDS[r]), label=core.day_labels[r], split="id", grid=GRID,
                       scenario=core.scenario, geometry=GRID.geometry(), cells=GRID.cells(),
                       init_pos=core.init_pos.numpy()) for r in rows]


@pytest.fixture(scope="module")
def replay(scn):
    core = make_core(scn)
    pre = collect(core, n_transitions=3 * (SLOTS - 1), cfg=PRE, seed=0, day_ids=DAY_IDS)
    return TransitionReplay.from_precollected(pre, grid=GRID, scenario=scn)


@pytest.fixture(scope="module")
def fitted(scn, tmp_path_factory):
    """One complete fit: (controller, manifest, run_dir, model file)."""
    run_dir = tmp_path_factory.mktemp("tdmpc_run")
    ctrl = TDMPCController(name="tdmpc", seed=0, options=settings())
    manifest = ctrl.fit(make_core(scn), run_dir=run_dir)
    ctrl.save(run_dir / "model.pt")
    return ctrl, manifest, run_dir, run_dir / "model.pt"


def learner_for(scn, seed=0, **kw) -> Learner:
    s = settings(**kw)
    torch.manual_seed(seed)
    ctrl = TDMPCController(name="tdmpc", seed=seed, options=s)
    return Learner(ctrl._build_model(GRID, scn), s, seed=seed)


# ----------------------------------------------------------------------------------- settings

def test_settings_resolve_merges_the_budget_and_reads_only_the_tdmpc_section():
    section = {**BASE, "precollect": {**dataclasses.asdict(PRE), "transitions": 60000}}
    config = {"methods": {"tdmpc": {**section, "budgets": {"smoke": {"steps": 12, "episodes": 1,
                                                                     "precollect": {"transitions": 1430}},
                                                           "demo": {"precollect": {"transitions": 2860}}}}}}
    s = resolve(config, profile="smoke")
    assert (s.steps, s.episodes, s.batch) == (12, 1, 16)
    assert s.precollect == dataclasses.replace(PRE, transitions=1430)     # the budget sets one key of precollect
    assert resolve(config, profile="demo").precollect.transitions == 2860
    assert resolve(config, profile="paper").precollect.transitions == 60000
    # DSWM's section is not read: its budget and its collection keys do not change TD-MPC's settings
    with_dswm = {**config, "dswm": {"budgets": {"smoke": {"transitions": 7}}, "training": {"collect_policy": "greedy"}}}
    assert resolve(with_dswm, profile="smoke") == s
    missing = {"methods": {"tdmpc": {k: v for k, v in section.items() if k != "precollect"}}}
    with pytest.raises(ConfigError, match=r"methods.tdmpc: missing key\(s\) \['precollect'\]"):
        resolve(missing, profile="paper")
    bad = {"methods": {"tdmpc": {**section, "precollect": {**section["precollect"], "collect_parallel": 0}}}}
    with pytest.raises(ConfigError, match=r"^config key methods\.tdmpc\.precollect\.collect_parallel: expected an "
                                          r"integer >= 1, found 0$"):
        resolve(bad, profile="paper")
    assert TDMPCController.options_from_plain(name="tdmpc", data=dataclasses.asdict(s)) == s
    with pytest.raises(ConfigError, match="n_elites"):
        settings(n_elites=64)
    with pytest.raises(ConfigError, match="gamma"):
        settings(gamma=1.5)
    with pytest.raises(ConfigError, match="seed_steps"):
        settings(seed_steps=30)            # no step left for the own episodes
    bad = {**config, "methods": {"tdmpc": {**section, "horizon": 0}}}
    with pytest.raises(ConfigError, match="horizon"):
        resolve(bad, profile="smoke")
    assert round_bounds(settings()) == [10, 20, 30]
    assert round_bounds(settings(episodes=0, seed_steps=0)) == [30]


# ----------------------------------------------------------------------------------- replay and TD targets

def test_recomputed_rewards_of_the_precollection_equal_the_environments(scn):
    core = make_core(scn)
    obs = core.reset([0, 2])
    rng = np.random.default_rng(0)
    fleet, acts, srs, rews = [obs["fleet"]], [], [], []
    for _ in range(SLOTS - 1):
        a = rng.uniform(-1, 1, size=(2, scn.n_uavs, 3)).astype(np.float32)
        out = core.step(a)
        fleet.append(out.obs["fleet"])
        acts.append(a)
        srs.append(out.sr)
        rews.append(out.reward)
    fleet, acts, srs, rews = (np.stack(x, 1) for x in (fleet, acts, srs, rews))
    assert (fleet[..., 4:6] > 0.5).any()          # some UAV returned or charged: those energies are checked too
    for j in range(2):
        got = episode_rewards(torch.as_tensor(fleet[j]), torch.as_tensor(acts[j]), torch.as_tensor(srs[j]), GRID, scn)
        np.testing.assert_allclose(got.numpy(), rews[j], atol=1e-5)


def test_td_target_bootstraps_on_the_truncated_last_transition(scn, replay):
    lrn = learner_for(scn)
    with torch.no_grad():                            # Q' heads start at zero: give the target non-zero values
        for head in (lrn.target.q1, lrn.target.q2):
            head[-1].weight.normal_(0.0, 1.0)
            head[-1].bias.fill_(-1.0)
    # A window that ends with the day's last decision: its next observation is the day's final one (slot T).
    horizon, t_last = 3, SLOTS - 2
    gen = torch.Generator().manual_seed(0)
    while True:
        b = replay.sample_windows(64, horizon, gen)
        hit = ((b["time"][-1] - replay.time_features(torch.tensor(t_last + 1))).abs() < 1e-6).all(-1)
        if hit.any():
            break
    i = int(torch.nonzero(hit)[0])
    assert not bool(b["terminated"][-1, i])          # truncated by the day's end, never terminated
    nxt = [b[k][-1, i:i + 1] for k in ("demand", "fleet", "time")]
    r = b["reward"][-1, i:i + 1]
    y = lrn.td_target(*nxt, r, torch.zeros(1, dtype=torch.bool))
    with torch.no_grad():                            # by hand: r + gamma * min(Q1', Q2')(z', pi(z'))
        z = lrn.target.encode(*nxt)
        a = torch.tanh(lrn.model.policy(z))
        za = torch.cat([z, a], -1)
        q = torch.minimum(lrn.target.q1(za), lrn.target.q2(za)).squeeze(-1)
    assert abs(float(0.95 * q)) > 0.1                # the bootstrap term is not negligible here
    torch.testing.assert_close(y, r + 0.95 * q)
    # the flag does switch the bootstrap off (the environment never sets it)
    torch.testing.assert_close(lrn.td_target(*nxt, r, torch.ones(1, dtype=torch.bool)), r)


def test_losses_encode_the_next_observations_once_for_the_consistency_and_td_targets(scn, replay):
    # losses() runs the target encoder once on o_1..o_H for both targets: its TD targets and consistency term
    # equal td_target's and the by-hand consistency on separately encoded targets.
    lrn = learner_for(scn)
    with torch.no_grad():
        for head in (lrn.target.q1, lrn.target.q2):
            head[-1].weight.normal_(0.0, 1.0)
            head[-1].bias.fill_(-1.0)
    b = replay.sample_windows(16, 3, torch.Generator().manual_seed(5))
    _, zs, m = lrn.losses(b)
    nxt = [b[k][1:] for k in ("demand", "fleet", "time")]
    y = lrn.td_target(*nxt, b["reward"], b["terminated"])
    assert abs(float(y.mean() - b["reward"].mean())) > 0.1          # the bootstrap term matters here
    assert m["td_target"] == pytest.approx(float(y.mean()), rel=1e-6)
    with torch.no_grad():
        z_target = lrn.target.encode(*nxt)
        cons = sum(0.5 ** t * ((zs[t + 1] - z_target[t]) ** 2).mean(-1) for t in range(3)).mean()
    assert m["consistency"] == pytest.approx(float(cons), rel=1e-5)


def test_the_replays_scaled_maps_give_the_raw_windows_losses_bit_for_bit(scn, replay):
    # sample_windows(scaled=True) reads the maps scaled once per buffer; the same draws, and a loss equal to the one
    # of the raw windows in every bit (the encoder then skips its own log1p, which gives the same floats).
    lrn = learner_for(scn)
    raw = replay.sample_windows(16, 3, torch.Generator().manual_seed(5))
    scaled = replay.sample_windows(16, 3, torch.Generator().manual_seed(5), scaled=True)
    assert "demand" not in scaled and set(scaled) - {"scaled_demand"} == set(raw) - {"demand"}
    assert torch.equal(scaled["scaled_demand"], torch.log1p(raw["demand"].clamp_min(0.0)))
    assert float(raw["demand"].max()) > 0.5            # log1p is not the identity on these maps
    for k in set(raw) - {"demand"}:
        assert torch.equal(scaled[k], raw[k]), k
    # the strips pad the day's first windows with its first map, as window_maps does
    row, start = torch.tensor([replay.rows[0]] * 3), torch.tensor([0, 1, 5])
    slot = start.unsqueeze(0) + torch.arange(3).unsqueeze(1)
    assert torch.equal(replay.scaled_windows(row, start, 3),
                       torch.log1p(replay.window_maps(row.expand(3, 3), slot).clamp_min(0.0)))
    total_raw, zs_raw, m_raw = lrn.losses(raw)
    total_scaled, zs_scaled, m_scaled = lrn.losses(scaled)
    assert torch.equal(total_raw, total_scaled) and m_raw == m_scaled
    assert all(torch.equal(a, b) for a, b in zip(zs_raw, zs_scaled))


def test_the_fleet_maps_bumps_are_exps_own_values_and_zero_where_exp_is_subnormal():
    d = torch.linspace(-20.0, 20.0, 4001)           # steps of 0.01: no d within 1e-3 of the cut at |d| = 13.216
    got, want = model_mod.bump(d), torch.exp(-0.5 * d ** 2)
    normal = want >= torch.finfo(torch.float32).tiny
    assert torch.equal(got[normal], want[normal])
    assert torch.equal(got[~normal], torch.zeros(int((~normal).sum())))
    assert int(((want > 0) & ~normal).sum()) > 200       # where exp gives subnormal numbers (|d| 13.22 .. 14.42)
    assert float(d[normal].abs().max()) == pytest.approx(13.21, abs=1e-4)


@pytest.mark.parametrize("scaled", [True, False])
def test_under_autocast_the_encoders_input_is_built_in_bfloat16_with_the_float32_ones_values(scn, replay, scaled):
    # autocast's conv would round a float32 input to bfloat16; the image is written in bfloat16 at once instead
    enc = learner_for(scn).model.encoder
    b = replay.sample_windows(16, 3, torch.Generator().manual_seed(5), scaled=scaled)
    maps = b["scaled_demand" if scaled else "demand"][0]
    full = enc.image(maps, b["fleet"][0], scaled)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        half = enc.image(maps, b["fleet"][0], scaled)
        fleet = model_mod.fleet_map(b["fleet"][0], GRID.rows, GRID.cols)    # its product runs in bfloat16 here
    assert full.dtype == torch.float32 and half.dtype == torch.bfloat16
    m = maps.shape[-3]
    assert torch.equal(half[:, :m], full[:, :m].to(torch.bfloat16))
    assert torch.equal(half[:, m], fleet.to(torch.bfloat16))
    assert not torch.equal(half.float(), full)          # the rounding is there to see


# ----------------------------------------------------------------------------------- learning

def test_gradient_steps_lower_the_told_loss_on_a_fixed_batch(scn, replay):
    lrn = learner_for(scn, batch=32)
    fixed = replay.sample_windows(64, 3, torch.Generator().manual_seed(123))
    with torch.no_grad():
        before, _, m0 = lrn.losses(fixed)
    for _ in range(300):
        lrn.train_step(replay)
    with torch.no_grad():
        after, _, m1 = lrn.losses(fixed)
    assert float(after) < 0.5 * float(before)
    assert m1["reward"] < 0.5 * m0["reward"] and m1["consistency"] < m0["consistency"]


def test_a_bfloat16_step_reads_bfloat16_maps_and_channels_last_convs_and_gives_the_float32_maps_step_bit_for_bit(
        scn, replay):
    # train_step samples the scaled maps in the step's dtype and the encoder lays a bfloat16 image out channels-last;
    # from the same weights and draws, updates from float32 maps through NCHW convs give the same weights, every bit
    lrn = {k: learner_for(scn, batch=32, matmul_dtype="bfloat16") for k in ("new", "old")}
    assert replay.scaled_maps(torch.bfloat16).dtype == torch.bfloat16
    assert torch.equal(replay.scaled_maps(torch.bfloat16), replay.scaled_maps().to(torch.bfloat16))
    plain = lambda self, img, fleet, time: self.head(torch.cat([self.conv(img), fleet.flatten(1), time], -1))
    seen = []
    conv = lrn["new"].model.encoder.conv
    hook = conv.register_forward_pre_hook(lambda mod, args: seen.append(args[0].is_contiguous(
        memory_format=torch.channels_last) and not args[0].is_contiguous()))
    metrics = {"new": [lrn["new"].train_step(replay) for _ in range(3)]}
    hook.remove()
    assert seen and all(seen)                        # the convs did read a channels-last image
    gen = lrn["old"].generator
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(model_mod.Encoder, "from_image", plain)
        metrics["old"] = [lrn["old"].update(replay.sample_windows(32, 3, gen, scaled=True)) for _ in range(3)]
    assert metrics["new"] == metrics["old"]
    for a, b in zip(lrn["new"].model.state_dict().values(), lrn["old"].model.state_dict().values()):
        assert torch.equal(a, b)
    with pytest.raises(ValueError, match=r"dtype torch\.bfloat16 needs scaled=True"):
        replay.sample_windows(4, 3, torch.Generator(), dtype=torch.bfloat16)


def test_bfloat16_steps_keep_float32_weights_and_state_and_follow_the_float32_losses(scn, replay):
    # matmul_dtype: bfloat16 runs the losses' forward under autocast: from the same weights and batches, its losses
    # stay within 2 % of float32's over 20 steps and still fall; weights, gradients and Adam's state stay float32.
    runs = {}
    for name in ("float32", "bfloat16"):
        lrn = learner_for(scn, batch=32, matmul_dtype=name)
        fixed = replay.sample_windows(64, 3, torch.Generator().manual_seed(123))
        with torch.no_grad():
            first = float(lrn.losses(fixed)[0])
        history = [lrn.train_step(replay) for _ in range(20)]
        with torch.no_grad():
            last = float(lrn.losses(fixed)[0])
        runs[name] = (first, last, history, lrn)
    (f0, f1, fh, _), (b0, b1, bh, lrn) = runs["float32"], runs["bfloat16"]
    assert b0 == pytest.approx(f0, rel=0.02) and b1 == pytest.approx(f1, rel=0.02)
    assert b1 < 0.7 * b0 and f1 < 0.7 * f0
    for key in ("total", "consistency", "reward", "value", "pi"):
        assert bh[-1][key] == pytest.approx(fh[-1][key], rel=0.05, abs=1e-3), key
    assert bh[-1] != fh[-1]                                  # the products did run in bfloat16
    tensors = [*lrn.model.parameters(), *lrn.target.parameters(), *(p.grad for p in lrn.model.parameters()
                                                                     if p.grad is not None)]
    tensors += [v for opt in (lrn.optim, lrn.pi_optim) for st in opt.state.values() for v in st.values()
                if torch.is_tensor(v) and v.is_floating_point()]
    assert {t.dtype for t in tensors} == {torch.float32}
    with pytest.raises(ConfigError, match=r"^config key methods\.tdmpc\.matmul_dtype: expected float32 or "
                                          r"bfloat16, found 'float16'$"):
        settings(matmul_dtype="float16")


def test_a_checkpoint_resumes_to_identical_next_step_losses(scn, replay, tmp_path):
    lrn = learner_for(scn)
    for _ in range(5):
        lrn.train_step(replay)
    torch.save(lrn.state_dict(), tmp_path / "ckpt.pt")
    next_a = [lrn.train_step(replay) for _ in range(2)]
    other = learner_for(scn, seed=5)                   # other weights and sampler until loaded
    other.load_state_dict(torch.load(tmp_path / "ckpt.pt", weights_only=False))
    next_b = [other.train_step(replay) for _ in range(2)]
    assert next_a == next_b
    assert other.step == lrn.step == 7


def test_an_interrupted_fit_resumes_to_the_uninterrupted_model(scn, fitted, tmp_path, monkeypatch):
    ctrl0, manifest0, _, _ = fitted
    calls = {"n": 0}
    real = learner_mod.Learner.train_step

    def failing(self, replay):
        calls["n"] += 1
        if calls["n"] == 17:                         # after the first own episode and the checkpoint at step 14
            raise KeyboardInterrupt
        return real(self, replay)

    monkeypatch.setattr(learner_mod.Learner, "train_step", failing)
    ctrl = TDMPCController(name="tdmpc", seed=0, options=settings())
    with pytest.raises(KeyboardInterrupt):
        ctrl.fit(make_core(scn), run_dir=tmp_path)
    monkeypatch.setattr(learner_mod.Learner, "train_step", real)
    blob = torch.load(tmp_path / "checkpoint.pt", weights_only=False)
    assert blob["learner"]["step"] == 14 and blob["run"]["rounds_done"] == 1
    manifest = TDMPCController(name="tdmpc", seed=0, options=settings()).fit(make_core(scn), run_dir=tmp_path)
    resumed = torch.load(tmp_path / "checkpoint.pt", weights_only=False)["learner"]["model"]
    for k, v in ctrl0.model.state_dict().items():
        assert torch.equal(resumed[k], v), k
    assert manifest["days"] == manifest0["days"] and manifest["history"] == manifest0["history"]


# ----------------------------------------------------------------------------------- MPPI

class Toy:
    """Latent = position in R^A; a moves it; reward -|z'-target|^2 (or 0); value -|z+a-target|^2 (or 0);
    the policy prior always says 0."""

    def __init__(self, target, *, reward=True, value=False):
        self.target, self.use_r, self.use_v = target, reward, value
        self.action_dim = target.shape[-1]

    def _t(self, z):
        return self.target.view(self.target.shape[0], *([1] * (z.dim() - 2)), -1)

    def next(self, z, a):
        z2 = z + a
        r = -((z2 - self._t(z)) ** 2).sum(-1) if self.use_r else torch.zeros(z.shape[:-1])
        return z2, r

    def q(self, z, a):
        v = -((z + a - self._t(z)) ** 2).sum(-1) if self.use_v else torch.zeros(z.shape[:-1])
        return v, v + 1.0                            # the minimum of the twins is the first

    def pi(self, z, std=0.0, generator=None):
        a = torch.zeros_like(z)
        return (a + std * torch.randn(a.shape, generator=generator)).clamp(-1, 1) if std > 0 else a


def toy_cfg(**kw):
    base = dict(horizon=3, n_samples=512, n_policy=16, n_elites=32, iterations=6, temperature=5.0, momentum=0.1,
                min_std=0.01, max_std=1.0, gamma=0.9)
    return MPPIConfig(**{**base, **kw})


def test_mppi_recovers_the_first_action_of_a_known_optimum_better_than_the_prior():
    target = torch.tensor([[0.6, -0.4, 0.2], [-0.7, 0.5, 0.0]])     # two problems planned at once
    model = Toy(target)
    res = mppi(model, torch.zeros(2, 3), cfg=toy_cfg(), generator=torch.Generator().manual_seed(0))
    assert res.action.shape == (2, 3) and res.mean.shape == (2, 3, 3)
    assert float((res.action - target).abs().max()) < 0.1          # optimum: reach the target at once
    prior = -((target) ** 2).sum(-1)                                # the prior's first action (0): one step's loss
    reached = -((res.action - target) ** 2).sum(-1)
    assert bool((reached > prior + 0.2).all())


def test_mppi_uses_the_td_value_at_the_end_of_the_horizon():
    target = torch.tensor([[0.5, -0.8, 0.3]])
    model = Toy(target, reward=False, value=True)                   # no reward: only Q(z_H, pi(z_H)) tells
    res = mppi(model, torch.zeros(1, 3), cfg=toy_cfg(horizon=1), generator=torch.Generator().manual_seed(1))
    assert float((res.action - target).abs().max()) < 0.1


def test_mppi_warm_start_shifts_the_previous_mean():
    target = torch.tensor([[0.5, -0.8, 0.3]])
    model = Toy(target, reward=False, value=False)                  # flat returns: the refit keeps the start
    prev = torch.arange(9, dtype=torch.float32).view(1, 3, 3) / 10.0
    res = mppi(model, torch.zeros(1, 3), cfg=toy_cfg(n_samples=4000, n_elites=4000, iterations=1, momentum=0.999,
                                                     n_policy=0), generator=torch.Generator().manual_seed(2),
               prev_mean=prev)
    expect = torch.cat([prev[:, 1:], torch.zeros(1, 1, 3)], 1)
    torch.testing.assert_close(res.mean, expect, atol=2e-3, rtol=0)


def test_bfloat16_planning_sums_float32_returns_close_to_the_float32_plans():
    torch.manual_seed(0)
    told = model_mod.TOLD(window=2, rows=4, cols=4, n_uavs=2, latent=8, hidden=32, channels=4)
    for p in told.parameters():   # the reward and Q heads start at zero: give every weight a value
        torch.nn.init.normal_(p, std=0.3)
    z = torch.randn(3, 8, generator=torch.Generator().manual_seed(1))
    cfg = toy_cfg(horizon=4, n_samples=256, n_elites=32)
    plans = {dtype: mppi(told, z, cfg=dataclasses.replace(cfg, matmul_dtype=dtype),
                         generator=torch.Generator().manual_seed(2)) for dtype in ("float32", "bfloat16")}
    low, full = plans["bfloat16"], plans["float32"]
    assert {t.dtype for t in low} == {torch.float32}
    gap = float((low.value - full.value).abs().max())
    assert 0.0 < gap < 0.02 * float(full.value.abs().max())   # products rounded to 8 bits; returns summed in float32


# ----------------------------------------------------------------------------------- diagnostics

def test_one_step_rewards_are_the_environments_and_leave_the_core_where_it_was(scn):
    core = make_core(scn)
    rng = np.random.default_rng(3)
    core.reset([0, 2])
    for _ in range(25):                              # far enough into the day that batteries and stations differ
        core.step(rng.uniform(-1, 1, size=(2, scn.n_uavs, 3)).astype(np.float32))
    cand = torch.as_tensor(rng.uniform(-1.5, 1.5, size=(6, scn.n_uavs, 3)), dtype=torch.float32)
    got = one_step_rewards(core, 1, cand)
    assert core.t == 25
    for i in range(len(cand)):                       # each candidate stepped for real in a copy of the core
        twin = copy.deepcopy(core)
        a = np.zeros((2, scn.n_uavs, 3), dtype=np.float32)
        a[1] = cand[i].numpy()
        assert abs(float(got[i]) - float(twin.step(a).reward[1])) < 1e-6
    assert float(got.max() - got.min()) > 0.01      # the candidates do differ


def test_rank_correlation_and_the_ranking_of_an_exact_and_a_reversed_reward_model(scn):
    assert rank_correlation([1, 2, 3, 4], [10, 20, 40, 30]) == pytest.approx(0.8)
    core = make_core(scn)
    obs = core.reset([0, 1])
    rng = np.random.default_rng(4)
    cand = torch.as_tensor(rng.uniform(-1, 1, size=(32, scn.n_uavs, 3)), dtype=torch.float32)
    true = one_step_rewards(core, 1, cand)

    class Stub:                                      # predicts the true reward times ``sign``
        def __init__(self, sign):
            self.sign = sign

        def encode(self, demand, fleet, time):
            return torch.zeros(demand.shape[0], 1)

        def next(self, z, a):
            return z, self.sign * one_step_rewards(core, 1, a.reshape(len(a), scn.n_uavs, 3))

    exact, reversed_ = (reward_ranking(Stub(s), core, obs, 1, cand) for s in (1.0, -1.0))
    assert exact.spearman == pytest.approx(1.0) and reversed_.spearman == pytest.approx(-1.0)
    assert exact.chosen == pytest.approx(float(true.max())) == pytest.approx(exact.best)
    assert reversed_.chosen == pytest.approx(float(true.min()))
    assert exact.mean == pytest.approx(float(true.mean()))


# ----------------------------------------------------------------------------------- the controller

def test_manifest_days_are_the_training_days_of_the_replays_episodes(scn, fitted):
    ctrl, manifest, _, _ = fitted
    rep = ctrl.replay
    assert manifest["days"] == [int(DAY_IDS[r]) for r in rep.rows] == rep.episode_days()
    assert manifest["days"] == [4, 7, 9, 4]          # DSWM's two pre-collected days, then two own episodes
    assert manifest["day_labels"] == ["2020-01-04", "2020-01-07", "2020-01-09", "2020-01-04"]
    assert rep.own == [False, False, True, True]
    assert manifest["n_transitions"] == (SLOTS - 1) * len(manifest["days"]) == rep.n_transitions
    assert manifest["transitions_per_day_episode"] == SLOTS - 1 and manifest["steps"] == 30
    assert manifest["read_test_data"] is False
    hist = manifest["history"]
    assert hist["step"][-1] == 30 and all(len(v) == len(hist["step"]) for v in hist.values())
    # the pre-collected episodes are exactly DSWM's (same heuristic, settings and seed)
    dswm = collect(make_core(scn), n_transitions=PRE.transitions, cfg=PRE, seed=0, day_ids=DAY_IDS)
    for a, b in zip(dswm.actions, rep.actions[:2], strict=False):
        assert torch.equal(a, b)


def test_actions_stay_in_the_box_and_displacements_within_d_max(scn, fitted):
    ctrl, _, _, _ = fitted
    core = make_core(scn)
    obs = core.reset([1, 2])
    ctrl.reset_batch(contexts(core, [1, 2]))
    longest = 0.0
    for _ in range(SLOTS - 1):
        before = core.state.pos.clone()
        active = core.state.status == 0
        a = ctrl.act_batch(obs)
        assert a.shape == (2, scn.n_uavs, 3) and a.dtype == np.float32
        assert np.abs(a).max() <= 1.0 and np.linalg.norm(a[..., :2], axis=-1).max() <= 1.0 + 1e-6
        obs = core.step(a).obs
        moved = torch.linalg.vector_norm(core.state.pos - before, dim=-1)[active]
        longest = max(longest, float(torch.cat([moved, torch.zeros(1)]).max()))
    assert 0.3 * scn.d_max_m < longest <= scn.d_max_m + 1e-3   # the fleet does move, never beyond D_max
    wild = project(torch.tensor([[[3.0, 3.0, -5.0], [0.3, -0.4, 0.2]]]))
    torch.testing.assert_close(wild, torch.tensor([[[0.5 ** 0.5, 0.5 ** 0.5, -1.0], [0.3, -0.4, 0.2]]]))


def run_day(ctrl, scn, rows, slots=8):
    core = make_core(scn)
    obs = core.reset(rows)
    ctrl.reset_batch(contexts(core, rows))
    out = []
    for _ in range(slots):
        a = ctrl.act_batch(obs)
        out.append(a)
        obs = core.step(a).obs
    return np.stack(out)


def test_same_seed_same_actions_and_the_saved_model_acts_alike(scn, fitted):
    ctrl, _, _, model_file = fitted
    loaded = [TDMPCController(name="tdmpc", seed=s, options=settings()) for s in (0, 0, 1)]
    for c in loaded:
        c.load(model_file)
    a0, a1, a2 = (run_day(c, scn, [0, 2]) for c in loaded)
    np.testing.assert_array_equal(a0, a1)
    np.testing.assert_array_equal(a0, run_day(ctrl, scn, [0, 2]))      # the fitted controller, same seed
    assert not np.array_equal(a0, a2)                                    # the seed does drive the sampling
    single = TDMPCController(name="tdmpc", seed=0, options=settings())
    single.load(model_file)
    core = make_core(scn)
    single.reset(contexts(core, [0])[0])
    one = single.act({k: v[0] for k, v in core.reset([0]).items()})
    assert one.shape == (scn.n_uavs, 3) and np.abs(one).max() <= 1.0
    with pytest.raises(ValueError, match="retrain"):
        TDMPCController(name="tdmpc", seed=0, options=settings(latent=8)).load(model_file)
