"""World-model training on demo data: losses fall, checkpoints are complete and resume exactly."""
import copy
import dataclasses
import shutil

import numpy as np
import pytest
import torch
import yaml

from dswm.sim.core import core_from_tensor
from dswm.methods.dswm.rssm import RSSMConfig
from dswm.methods.base import DayContext
from dswm.methods.classical import GreedyController
from dswm.methods.collect import collect
from dswm.methods.dswm.settings import resolve
from dswm.methods.dswm.training import TrainConfig, load_checkpoint, loss_function, save_training_figure, train
from dswm.methods.search import SearchSettings, configured_search
from dswm.methods.dswm.world_model import WorldModel, WorldModelConfig
from prep.pipeline import generate_demo
from prep.tensor import load

from conftest import ROOT, dataset_of, prepare_from_config


@pytest.fixture(scope="module")
def demo_core(tmp_path_factory):
    """A training-days core over two Milan demo training days (generated and prepared by the prep code)."""
    config = yaml.safe_load((ROOT / "config.yaml").read_text())
    tmp = tmp_path_factory.mktemp("milan_demo")
    generate_demo(dataset_of(config, "milan"), "milan", tmp / "raw")
    prepare_from_config(config, "milan", raw=[str(tmp / "raw")], out_dir=tmp / "data", reference_meta=None)
    tensor = load(tmp / "data")
    from dswm.sim.scenario import load_scenario
    scenario = load_scenario(ROOT / "config.yaml", standin=True)  # u a number where config.yaml says calibrate
    core = core_from_tensor(tensor, scenario, tensor.train_days[:2])
    return core, config


def _tiny(core, service_head="physics"):
    cfg = WorldModelConfig(rssm=RSSMConfig(deter=32, stoch=8, hidden=32, embed=32, min_std=0.1,
                                           free_bits=0.1, kl_dyn=0.8, kl_rep=0.2),
                           ensemble=3, demand_hidden=16, demand_rank=8, enc_channels=4, head_hidden=32, ema_nu=0.95,
                           lambda_var=1.0, m_var=0.1, beta_kl=1.0, lambda_lpr=1.0, lambda_cal=0.1, lambda_serve=1.0,
                           service_head=service_head)
    return WorldModel(cfg=cfg, rows=core.grid.rows, cols=core.grid.cols, n_uavs=core.scenario.n_uavs, window=7,
                      cells=core.grid.cells(), params=core.params)


def _train_cfg(**kw):
    base = dict(lr=1e-3, batch=4, seq_len=8, grad_clip=100.0, collect_policy="lloyd", collect_parallel=2,
                explore_std=0.3, bw_explore_std=0.5, collect_search=SearchSettings(sweeps=1, lattice=5, refine=0,
                                                                                   bw_logits=()),
                log_points=10_000, checkpoint_every=1000, compile=False)
    base.update(kw)
    return TrainConfig(**base)


@pytest.fixture(scope="module")
def replay(demo_core):
    core, _ = demo_core
    rep = collect(core, n_transitions=286, cfg=_train_cfg(), seed=0, day_ids=core.day_ids)
    return rep


def test_collection_records_training_days(demo_core, replay):
    core, _ = demo_core
    assert replay.n_transitions == 2 * 143
    assert sorted(replay.episode_days()) == sorted(core.day_ids.tolist())
    batch = replay.sample(3, 8, torch.Generator().manual_seed(0))
    # the observation window of the replay equals the environment's own observation at that slot
    obs = core.reset([replay.rows[0]])
    for _ in range(9):
        obs = core.step(np.zeros((1, core.scenario.n_uavs, 3), np.float32)).obs
    win = replay.window_maps(torch.tensor([replay.rows[0]]), torch.tensor([9]))[0]
    np.testing.assert_array_equal(win.numpy(), obs["demand"][0])
    assert batch["demand"].shape == (8, 3, 7, core.grid.rows, core.grid.cols)


def test_greedy_collection_moves_the_fleet_with_the_configured_search(demo_core):
    """``collect_policy: greedy`` steps the training days with the greedy baseline running ``collect_search``
    (config.yaml: one sweep on a 5x5 lattice, the demand-proportional split)."""
    core, config = demo_core
    training = resolve(config["dswm"], method="dswm", profile="smoke",
                       search=configured_search(config, "smoke")[0]).training
    assert training.collect_search == SearchSettings(sweeps=1, lattice=5, refine=0, bw_logits=())
    quiet = dict(explore_std=0.0, bw_explore_std=0.0, collect_search=training.collect_search)
    lloyd = collect(core, n_transitions=143, cfg=_train_cfg(**quiet), seed=0, day_ids=core.day_ids)
    greedy = collect(core, n_transitions=143, cfg=_train_cfg(collect_policy="greedy", **quiet), seed=0,
                     day_ids=core.day_ids)
    assert greedy.n_transitions == lloyd.n_transitions == 143
    a, b = torch.cat(greedy.actions), torch.cat(lloyd.actions)
    assert a.shape == b.shape == (143, core.scenario.n_uavs, 3) and float(a.abs().max()) <= 1.0
    assert float((a[..., :2] - b[..., :2]).abs().max()) > 0.05  # another policy moved the fleet
    # the first move is the greedy baseline's with the configured search
    ctrl = GreedyController(name="greedy", options=training.collect_search)
    ctrl.reset_batch([DayContext(dataset=core.dataset, day=0, label=core.day_labels[0], split="train", grid=core.grid,
                                 scenario=core.scenario, geometry=core.geom, cells=core.cells,
                                 init_pos=core.init_pos.cpu().numpy())])
    first = ctrl.act_batch(core.reset([0]))[0]
    np.testing.assert_allclose(greedy.actions[0][0, :, :2].numpy(), np.clip(first[:, :2], -1.0, 1.0), atol=1e-6)


@pytest.mark.parametrize("head", ["physics", "mlp"])
def test_training_lowers_demand_and_service_losses(demo_core, replay, tmp_path, head):
    core, _ = demo_core
    torch.manual_seed(0)
    model = _tiny(core, head)
    model.set_normalizer(replay.demand)
    hist = train(model, replay, steps=300, cfg=_train_cfg(), seed=0, checkpoint=tmp_path / "ckpt.pt")
    dem, serve = np.asarray(hist["losses/dem"]), np.asarray(hist["losses/serve"])
    assert len(dem) == 300 and np.isfinite(dem).all() and np.isfinite(serve).all()
    assert dem[-30:].mean() < 0.5 * dem[:30].mean()
    assert serve[-30:].mean() < 0.7 * serve[:30].mean()
    save_training_figure(hist, tmp_path / "diag.png")
    assert (tmp_path / "diag.png").stat().st_size > 10_000


def test_checkpoint_is_complete_and_resumes_to_identical_losses(demo_core, replay, tmp_path):
    core, _ = demo_core
    cfg = _train_cfg(checkpoint_every=3)
    extra = {"run": "resume-test"}

    def fresh(seed):
        torch.manual_seed(seed)
        m = _tiny(core)
        m.set_normalizer(replay.demand)
        return m

    straight = train(fresh(0), replay, steps=5, cfg=cfg, seed=7, checkpoint=tmp_path / "a.pt", extra=extra)
    interrupted = train(fresh(0), replay, steps=3, cfg=cfg, seed=7, checkpoint=tmp_path / "b.pt", extra=extra)
    shutil.copy(tmp_path / "b.pt", tmp_path / "c.pt")
    blob = torch.load(tmp_path / "c.pt", weights_only=False)
    assert {"model", "optimizer", "torch_rng", "sample_rng", "step", "history"} <= set(blob)
    assert blob["step"] == 3 and "encoder.dem_mean" in blob["model"] and "teacher.rssm.gru.weight_hh" in blob["model"]
    # a different initialization is overwritten by the checkpoint: the next losses are the uninterrupted ones
    resumed = train(fresh(123), replay, steps=5, cfg=cfg, seed=7, checkpoint=tmp_path / "c.pt", extra=extra)
    assert resumed["step"] == [1, 2, 3, 4, 5]
    for key in ("losses/loss", "losses/dem", "losses/serve", "losses/kl", "losses/lpr_pred"):
        assert resumed[key][3:] == straight[key][3:], key
    assert interrupted["losses/loss"] == straight["losses/loss"][:3]
    # a checkpoint of another run (different identity) is not resumed
    other = train(fresh(0), replay, steps=5, cfg=cfg, seed=7, checkpoint=tmp_path / "c.pt", extra={"run": "x"})
    assert other["losses/loss"] == straight["losses/loss"]
    # loading restores the normalizer buffers (they are not parameters)
    m = fresh(5)
    with torch.no_grad():
        m.encoder.dem_mean.fill_(123.0)
    load_checkpoint(tmp_path / "a.pt", model=m)
    assert float(m.encoder.dem_mean) == float(blob["model"]["encoder.dem_mean"]) != 123.0


def test_compiled_training_computes_the_eager_loss_and_gradients_and_repeats_itself(demo_core, replay, tmp_path):
    """``dswm.training.compile`` (the paper profile's): with the Gaussian draws set aside (the posterior and prior
    means, as filtering uses), the compiled loss and every parameter's gradient are the eager ones up to float
    rounding; a compiled run repeats itself with its seed, through a checkpoint too."""
    core, _ = demo_core
    torch.manual_seed(0)
    model = _tiny(core)
    model.set_normalizer(replay.demand)
    batch = replay.sample(2, 3, torch.Generator().manual_seed(3))  # short sequences: a short compile
    rssm = type(model.rssm)
    draw = rssm._gaussian
    rssm._gaussian = lambda self, stats, sample: draw(self, stats, False)  # no draws: both sides are deterministic
    try:
        grads = []
        for compiled in (False, True):
            model.zero_grad(set_to_none=True)
            loss, metrics = loss_function(model, compiled)(batch)
            loss.backward()
            grads.append((float(loss), {k: float(v) for k, v in metrics.items()},
                          {n: p.grad.clone() for n, p in model.named_parameters() if p.grad is not None}))
    finally:
        rssm._gaussian = draw
    (eager, eager_m, eager_g), (comp, comp_m, comp_g) = grads
    assert comp == pytest.approx(eager, rel=1e-4) and eager > 0
    for k in eager_m:
        assert comp_m[k] == pytest.approx(eager_m[k], rel=1e-3, abs=1e-6), k
    assert eager_g.keys() == comp_g.keys() and len(eager_g) > 20
    for name, g in eager_g.items():
        torch.testing.assert_close(comp_g[name], g, rtol=1e-3, atol=1e-5, msg=name)
    assert any(float(g.abs().max()) > 1e-3 for g in eager_g.values())

    cfg = _train_cfg(compile=True, checkpoint_every=2, batch=2, seq_len=3)

    start = copy.deepcopy(model.state_dict())

    def fresh():  # the same model object, so that its compiled loss is reused (guards on the module), reset
        model.load_state_dict(start)
        return model

    first = train(fresh(), replay, steps=4, cfg=cfg, seed=7, checkpoint=tmp_path / "a.pt")
    assert np.isfinite(first["losses/loss"]).all()
    eager_run = train(fresh(), replay, steps=4, cfg=dataclasses.replace(cfg, compile=False), seed=7,
                      checkpoint=tmp_path / "e.pt")
    assert first["losses/loss"] != eager_run["losses/loss"]  # its own draws: compiled runs are their own
    # a second run with the seed, interrupted after 2 steps and resumed: the first run's losses, draws included
    train(fresh(), replay, steps=2, cfg=cfg, seed=7, checkpoint=tmp_path / "c.pt")
    resumed = train(fresh(), replay, steps=4, cfg=cfg, seed=7, checkpoint=tmp_path / "c.pt")
    assert resumed["losses/loss"] == first["losses/loss"]
