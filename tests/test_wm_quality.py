"""DSWM's own figures: the training history file, the world-model quality computation (replay, open-loop demand
error, imagined return) and the drawing functions of the training, world-model quality and qualitative figures."""
import dataclasses
import math

import numpy as np
import polars as pl
import pytest
import torch
import yaml

from conftest import ROOT
from dswm import settings as runconfig
from dswm.figures import qualitative as q, regions
from dswm.figures.common import read_csv
from dswm.figures.training import draw_training
from dswm.figures.wm_quality import draw_wm_quality, rank_correlation, rmse_table
from dswm.methods.base import Controller
from dswm.methods.dswm import quality
from dswm.methods.dswm.world_model import WorldModel
from dswm.pipeline.history import history_frame, read_histories, write_history
from dswm.pipeline.wm import days_to_replay
from dswm.protocol.replay import replay
from dswm.settings import EvalDayLimits
from dswm.sim.core import Grid
from dswm.sim.physics import ServiceParams
from prep.tensor import DemandTensor, GridSpec

ROWS = COLS = 6


def out_paths(tmp_path, name):
    return {ext: tmp_path / f"{name}.{ext}" for ext in ("png", "pdf", "csv")}


# ---- the training history file ----------------------------------------------------------------------------------
def test_history_file_round_trip_keeps_steps_and_every_series(tmp_path):
    history = {"losses/loss": [3.0, 2.5, 2.25], "losses/dem": [0.5, 0.25, 0.125]}
    written = write_history(tmp_path / "h.parquet", history, [2, 4, 6], dataset="milan", method="dswm", seed=1)
    back = read_histories([tmp_path / "h.parquet"])
    assert back.equals(written)
    assert back["step"].to_list() == [2, 4, 6] and back["losses/dem"].to_list() == [0.5, 0.25, 0.125]
    assert set(back["seed"]) == {1} and set(back["dataset"]) == {"milan"}
    assert not list(tmp_path.glob(".h.parquet*"))  # no temporary file left
    assert history_frame({"x": [1.0, 2.0]}, None, dataset="d", method="m", seed=0)["step"].to_list() == [0, 1]
    with pytest.raises(ValueError, match="has 2 values, expected 3"):
        history_frame({"losses/loss": [1.0, 2.0]}, [1, 2, 3], dataset="milan", method="dswm", seed=0)


def test_training_figure_draws_the_mean_and_std_over_seeds(tmp_path):
    rows = []
    for seed, level in ((0, 1.0), (1, 3.0)):
        rows.append(history_frame({k: [level * (i + 1) for i in range(3)] for k in
                                   ("losses/loss", "losses/dem", "losses/kl", "losses/lpr_pred", "losses/lpr_var")},
                                  [10, 20, 30], dataset="milan", method="dswm", seed=seed))
    out = out_paths(tmp_path, "training")
    draw_training(pl.concat(rows), datasets=["milan"], labels={"milan": "Milan"}, profile="smoke", source="demo",
                  out=out)
    assert all(p.stat().st_size > 0 for p in out.values())
    csv = read_csv(out["csv"]).filter((pl.col("series") == "losses/dem") & (pl.col("step") == 20))
    assert csv["value"].item() == pytest.approx(4.0)      # mean of 2 and 6
    assert csv["value_std"].item() == pytest.approx(2.0)  # population std over the two seeds
    assert csv["seeds"].item() == 2


# ---- the quality computation ------------------------------------------------------------------------------------
def test_demand_errors_of_a_perfect_a_shifted_and_the_persistence_map():
    demand = np.arange(10, dtype=np.float64)[:, None] * np.ones((1, 4))  # x_t = t in every cell
    starts = np.array([0, 3, 5])
    truth = np.stack([demand[starts + k] for k in (1, 2, 3)])
    perfect = quality.demand_errors(truth, demand, starts, rho=0.0)
    assert perfect["mse_model"].tolist() == [0.0, 0.0, 0.0] and perfect["mse_anchored"].tolist() == [0.0, 0.0, 0.0]
    assert perfect["mse_persistence"].tolist() == [1.0, 4.0, 9.0]  # x_t misses x_{t+k} by k
    shifted = quality.demand_errors(truth + 0.5, demand, starts, rho=0.5)
    assert shifted["mse_model"] == pytest.approx([0.25] * 3)
    # anchored = 0.5 x_t + 0.5 (x_{t+k} + 0.5): error 0.25 - k / 2
    assert shifted["mse_anchored"] == pytest.approx([(0.25 - k / 2) ** 2 for k in (1, 2, 3)])


class Wander(Controller):
    """Random moves, the same every run (seeded per day): a cheap controller to replay."""

    def reset(self, ctx):
        self.rng = np.random.default_rng(1000 + ctx.day)
        self.k = ctx.scenario.n_uavs

    def act(self, obs):
        return self.rng.uniform(-1.0, 1.0, size=(self.k, 3)).astype(np.float32)


def toy_tensor():
    rng = np.random.default_rng(3)
    demand = rng.gamma(0.8, 1.0, size=(5, 144, ROWS, COLS)).astype(np.float32) + 0.01
    days = [{"index": i, "label": f"d{i}", "split": "train" if i < 3 else "test", "weekday": i, "weekend": i == 4}
            for i in range(5)]
    meta = {"dataset": "toy", "source": "demo", "days": days, "slots_per_day": 144,
            "eval_days": {"id": [3], "ood": [4]}, "grid": {"rows": ROWS, "cols": COLS, "cell_m": 235.0}}
    return DemandTensor(demand=demand, meta=meta, grid=GridSpec(rows=ROWS, cols=COLS, cell_m=235.0))


@pytest.fixture(scope="module")
def played(scenario):
    sc = dataclasses.replace(scenario, n_uavs=4, demand_intensity=150.0)
    tensor = toy_tensor()
    plays, result = replay(tensor=tensor, controller=Wander(name="wander"), scenario=sc, seed=0,
                           days={"id": [3], "ood": [4]}, profile="smoke", device="cpu", progress_interval_s=60.0)
    return sc, tensor, plays, result


@pytest.fixture(scope="module")
def model(played):
    config = yaml.safe_load((ROOT / "config.yaml").read_text())
    config["profile"] = "smoke"
    wm = runconfig.resolve(config).methods["dswm"].options.world_model
    wm = dataclasses.replace(wm, rssm=dataclasses.replace(wm.rssm, deter=16, stoch=4, hidden=16, embed=16),
                             ensemble=2, demand_hidden=8, demand_rank=4, enc_channels=4, head_hidden=16)
    sc = played[0]
    torch.manual_seed(0)
    grid = Grid(rows=ROWS, cols=COLS, cell_m=235.0)
    return WorldModel(cfg=wm, rows=ROWS, cols=COLS, n_uavs=sc.n_uavs, window=sc.obs_window + 1, cells=grid.cells(),
                      params=ServiceParams.from_scenario(sc)).eval()


def test_replay_records_what_the_evaluation_played(played):
    sc, tensor, plays, result = played
    assert [(p.day, p.split) for p in plays] == [(3, "id"), (4, "ood")]
    for play, row in zip(plays, result.days.iter_rows(named=True)):
        assert play.actions.shape == (143, 4, 3) and len(play.obs) == 143 and play.sr.shape == (144,)
        assert play.sr.mean() == pytest.approx(row["sr_mean"], abs=1e-6)  # the same play as the evaluation's (float32)
        assert np.array_equal(play.obs[7]["demand"][-1], tensor.demand[play.day, 7])  # o_t holds x_t
    assert play.actions[0].tolist() == np.random.default_rng(1004).uniform(-1, 1, (4, 3)).astype(np.float32).tolist()


def perfect(model, play, calls):
    """Make ``model``'s demand heads answer the realized maps of the rows they are asked for, in call order."""
    maps = iter(calls)
    demand = torch.as_tensor(play.demand.reshape(play.demand.shape[0], -1))
    model.demand_members = lambda feat: demand[next(maps)].unsqueeze(0).expand(2, -1, -1)


def test_a_model_that_imagines_the_truth_has_zero_rmse_and_imagines_the_realized_return(played, model):
    sc, tensor, plays, _ = played
    play, horizon = plays[0], 4
    posts = quality.posteriors(model, play)
    starts = np.arange(0, 143 - horizon + 1)
    try:
        perfect(model, play, [starts + k for k in range(1, horizon + 1)])
        pred = quality.open_loop_maps(model, posts, play.actions, starts, horizon)
        errors = quality.demand_errors(pred, play.demand.reshape(144, -1), starts, rho=0.0)
        assert errors["mse_model"] == pytest.approx([0.0] * horizon, abs=1e-12)
        assert errors["mse_persistence"][0] > 0.1
        perfect(model, play, [np.arange(1, 144)] * 2)
        sr_hat, reward = quality.imagined_rewards(model, posts, play, grid=Grid(rows=ROWS, cols=COLS, cell_m=235.0),
                                                  scenario=sc, rho=0.0, lambda_u=1.0)
    finally:
        del model.demand_members
    # the fleet moved by the environment's rules, the true map, the executed bandwidth logits: the realized SR
    assert np.abs(sr_hat - play.sr[1:]).max() < 1e-4
    assert np.array_equal(reward, sr_hat)  # one head's copies agree: no uncertainty penalty


def test_day_quality_of_an_untrained_model(played, model):
    sc, _, plays, _ = played
    out = quality.day_quality(model, plays[1], grid=Grid(rows=ROWS, cols=COLS, cell_m=235.0), scenario=sc,
                              horizon=24, rho=0.95, lambda_u=1.0)
    assert out["starts"].tolist() == list(range(120)) and out["mse_model"].shape == (24,)
    assert np.isnan(out["one_step"][0]).all() and np.isfinite(out["one_step"][1:]).all()
    assert out["one_step"].shape == (144, ROWS, COLS) and out["sr"].tolist() == plays[1].sr[1:].tolist()
    assert (out["reward"] <= out["sr_hat"] + 1e-7).all()  # the penalty only lowers the planner's reward
    with pytest.raises(ValueError, match="horizon"):
        quality.day_quality(model, plays[1], grid=Grid(rows=ROWS, cols=COLS, cell_m=235.0), scenario=sc,
                            horizon=144, rho=0.95, lambda_u=1.0)


def test_days_to_replay_cuts_each_split_of_the_main_days():
    days = pl.DataFrame({"day": [10, 11, 12, 13, 14], "split": ["id", "id", "id", "ood", "ood"]})
    assert days_to_replay(days, EvalDayLimits(id=2, ood=0), "d") == {"id": [10, 11]}
    assert days_to_replay(days, EvalDayLimits(id=None, ood=1), "d") == {"id": [10, 11, 12], "ood": [13]}
    with pytest.raises(ValueError, match="no evaluated day left"):
        days_to_replay(days, EvalDayLimits(id=0, ood=0), "d")


# ---- the world-model quality figure -----------------------------------------------------------------------------
def quality_frames(n_days):
    rmse, returns = [], []
    for seed, scale in ((0, 0.1), (1, 0.2)):
        for day in range(n_days):
            for step in (1, 2, 3):
                rmse.append({"seed": seed, "day": day, "step": step, "starts": 120, "mse_model": (scale * step) ** 2,
                             "mse_anchored": 0.01, "mse_persistence": 0.04 * step, "mbps_per_unit": 10.0})
            returns.append({"seed": seed, "day": day, "label": f"d{day}", "split": "id",
                            "imagined_sr": 0.7 + 0.01 * day + seed * 0.001,
                            "realized_sr": 0.6 + 0.02 * day + seed * 0.002})
    return pl.DataFrame(rmse), pl.DataFrame(returns)


def test_wm_quality_figure_writes_rmse_per_step_and_spearman(tmp_path):
    rmse, returns = quality_frames(n_days=2)
    out = out_paths(tmp_path, "wm_quality")
    draw_wm_quality(rmse, returns, dataset_label="Milan", profile="smoke", source="demo", out=out)
    assert all(p.stat().st_size > 0 for p in out.values())
    csv = read_csv(out["csv"])
    row = csv.filter((pl.col("panel") == "a") & (pl.col("series") == "model") & (pl.col("step") == 3))
    assert row["rmse"].item() == pytest.approx(0.45)          # mean of the seeds' 0.3 and 0.6
    assert row["rmse_std"].item() == pytest.approx(0.15)
    assert row["rmse_mbps"].item() == pytest.approx(4.5)
    spearman = csv.filter(pl.col("series") == "spearman")
    assert spearman["r_s"].item() == pytest.approx(1.0) and spearman["points"].item() == 4
    assert math.isnan(spearman["r_s_seed_mean"].item())  # two days a seed: no per-seed r_s
    assert csv.filter(pl.col("series") == "seed-day").height == 4


def test_rank_correlation_per_seed_and_rmse_weights_days_by_their_starts():
    _, returns = quality_frames(n_days=3)
    flipped = returns.with_columns(pl.when(pl.col("seed") == 1).then(-pl.col("realized_sr"))
                                   .otherwise(pl.col("realized_sr")).alias("realized_sr"))
    ranks = rank_correlation(flipped)
    assert ranks["seeds_ranked"] == 2 and ranks["r_s_seed_mean"] == pytest.approx(0.0)
    assert ranks["r_s_seed_std"] == pytest.approx(1.0)
    rmse = pl.DataFrame({"seed": [0, 0], "day": [0, 1], "step": [1, 1], "starts": [30, 10], "mse_model": [1.0, 5.0],
                         "mse_anchored": [0.0, 0.0], "mse_persistence": [0.0, 0.0], "mbps_per_unit": [1.0, 1.0]})
    assert rmse_table(rmse).filter(pl.col("series") == "model")["rmse"].item() == pytest.approx(math.sqrt(2.0))


# ---- the qualitative figures ------------------------------------------------------------------------------------
def test_busy_slot_skips_slot_zero():
    maps = np.ones((5, 2, 2))
    maps[0] *= 9.0
    maps[3] *= 2.0
    assert regions.busy_slot(maps) == 3


def test_milan_crop_outline_on_the_real_grid():
    ids, rings = regions.read_milan_grid()
    assert ids.tolist() == list(range(1, 10001)) and rings.shape == (10000, 4, 2)
    grid = {"rows": 20, "cols": 20, "first_row": 40, "first_col": 40, "full_cols": 100}
    assert regions.milan_crop_squares(grid)[0, 0] == 4041 and regions.milan_crop_squares(grid)[-1, -1] == 5960
    outline = regions.milan_crop_outline(ids, rings, grid)
    sw, ne = rings[4040], rings[5959]   # squares 4041 (south-west corner of the crop) and 5960 (north-east)
    assert outline[0] == pytest.approx([sw[:, 0].min(), sw[:, 1].min()])
    assert outline[2] == pytest.approx([ne[:, 0].max(), ne[:, 1].max()])
    # 20 squares of about 235 m: the crop spans about 4.7 km north-south
    assert (outline[2, 1] - outline[0, 1]) * 111_195 == pytest.approx(4700, rel=0.02)


def test_region_figure_draws_the_crop_maps_and_checks_the_crop(tmp_path):
    region = np.zeros((8, 9))
    region[2:5, 3:6] = 5.0
    meta = {"dataset": "shanghai", "crop": {"first_row": 2, "first_col": 3}, "grid": {"rows": 3, "cols": 3}}
    regions.check_region(region, meta)
    with pytest.raises(ValueError, match="densest 3x3 window"):
        regions.check_region(region, {**meta, "crop": {"first_row": 0, "first_col": 0}})
    true = np.arange(9.0).reshape(3, 3)
    out = out_paths(tmp_path, "qualitative_shanghai")
    q.draw_region(dataset="shanghai", label="Shanghai", region=region, origin=(2, 3), true=true,
                  weekday=np.ones((3, 3)), weekend=np.full((3, 3), 2.0), cell_m=470.0, region_what="starts",
                  when="d0 12:00", counts=(5, 2), weekend_word="weekend", profile="smoke", source="demo", out=out)
    csv = read_csv(out["csv"])
    assert csv.filter((pl.col("panel") == "true") & (pl.col("row") == 2) & (pl.col("col") == 1))["value"].item() == 7.0
    assert csv.filter(pl.col("panel") == "region")["value"].sum() == pytest.approx(45.0)
    assert all(p.stat().st_size > 0 for p in out.values())


def test_day_profiles_split_weekdays_from_weekends():
    demand = np.stack([np.full((2, 1, 1), v) for v in (1.0, 3.0, 5.0)])
    meta = {"dataset": "toy", "days": [{"weekend": False}, {"weekend": True}, {"weekend": False}]}
    weekday, weekend, n_wd, n_we = regions.day_profiles(demand, meta)
    assert weekday.item() == 3.0 and weekend.item() == 3.0 and (n_wd, n_we) == (2, 1)
