"""Per-day evaluation: the day score recomputed from the physics, energy from the hover power, bookkeeping."""
import dataclasses

import numpy as np
import polars as pl
import pytest
import torch

from dswm.methods.search import SearchSettings
from dswm.methods.classical import GreedyController, StaticController
from dswm.sim.core import Grid
from dswm.protocol.evaluation import DAY_COLUMNS, eval_days_hash, evaluate, split_summary
from dswm.sim.core import initial_deployment
from dswm.sim.physics import ServiceParams, served_ratio
from prep.tensor import DemandTensor, GridSpec

HOVER_W = 168.48  # docs/PROTOCOL.md §1: hover power of the rotary-wing model

RUN = {"device": "cpu", "batch_days": True, "progress_interval_s": 5.0}  # how each call runs, not what it computes


def toy_tensor(n_train=3, n_test=4, rows=6, cols=6, seed=0):
    """A small prepared-tensor stand-in: days 0..n_train-1 train, the rest test; ID = test 0,1; OOD = 2,3."""
    rng = np.random.default_rng(seed)
    n = n_train + n_test
    demand = rng.gamma(0.6, 1.0, size=(n, 144, rows, cols)).astype(np.float32)
    days = [{"index": i, "label": f"d{i}", "split": "train" if i < n_train else "test", "weekday": i % 7,
             "weekend": False} for i in range(n)]
    meta = {"dataset": "toy", "source": "demo", "days": days, "slots_per_day": 144,
            "eval_days": {"id": [n_train, n_train + 1], "ood": [n_train + 2, n_train + 3]},
            "grid": {"rows": rows, "cols": cols, "cell_m": 235.0}}
    return DemandTensor(demand=demand, meta=meta, grid=GridSpec(rows=rows, cols=cols, cell_m=235.0))


@pytest.fixture
def big_battery(make_scenario):
    """K=4 and a battery no day can drain, so a static fleet stays where it starts all day."""
    return make_scenario(n_uavs=4, battery_j=1.0e12, demand_intensity=150.0)


def test_static_day_score_is_the_mean_of_144_served_ratios_of_the_fixed_fleet(big_battery):
    t = toy_tensor()
    res = evaluate(tensor=t, controller=StaticController(name="static"), scenario=big_battery, seed=0,
                   limits={"id": None, "ood": None}, profile="smoke", **RUN)
    grid = Grid(rows=6, cols=6, cell_m=235.0)
    pos = torch.tensor(initial_deployment(t, grid, big_battery))[None]
    params = ServiceParams.from_scenario(big_battery)
    df = res.days
    assert df.columns == DAY_COLUMNS
    assert df["day"].to_list() == [3, 4, 5, 6] and df["split"].to_list() == ["id", "id", "ood", "ood"]
    for row in df.iter_rows(named=True):
        x = torch.tensor(t.demand[row["day"]].reshape(144, -1))
        sr = served_ratio(x, pos.expand(144, -1, -1), torch.ones(144, 4, dtype=torch.bool), grid.cells(),
                          params=params)
        assert row["sr_mean"] == pytest.approx(float(sr.mean()), abs=1e-6)
        # a static fleet hovers: K * P_hover * 600 s per slot
        assert row["energy_kj_per_slot"] == pytest.approx(4 * HOVER_W * 600 / 1000, rel=1e-3)
        assert row["energy_efficiency"] == pytest.approx(row["sr_mean"] / (row["energy_kj_per_slot"] / 1000))
        assert 0 < row["jain"] <= 1 and row["plan_ms_per_slot"] >= 0
        assert (row["method"], row["dataset"], row["profile"], row["data_source"], row["seed"]) == \
            ("static", "toy", "smoke", "demo", 0)
    assert df["eval_days_hash"].n_unique() == 1 and df["obs_spec_hash"].n_unique() == 1
    assert df["scenario_hash"][0] == big_battery.hash()


def test_profile_limits_cut_each_split_and_change_the_eval_days_hash(big_battery):
    t = toy_tensor()
    full = evaluate(tensor=t, controller=StaticController(name="static"), scenario=big_battery, seed=0,
                    limits={"id": None, "ood": None}, profile="demo", **RUN).days
    cut = evaluate(tensor=t, controller=StaticController(name="static"), scenario=big_battery, seed=0,
                   limits={"id": 1, "ood": 1}, profile="smoke", **RUN).days
    assert cut["day"].to_list() == [3, 5]
    assert cut["eval_days_hash"][0] != full["eval_days_hash"][0]
    assert cut["eval_days_hash"][0] == eval_days_hash("toy", {"id": [3], "ood": [5]}, [f"d{i}" for i in range(7)])
    # the same day scores the same whatever else is evaluated with it
    assert cut.filter(pl.col("day") == 5)["sr_mean"][0] == pytest.approx(
        full.filter(pl.col("day") == 5)["sr_mean"][0], abs=1e-7)


def test_trajectories_hold_positions_per_slot_of_the_first_id_and_ood_day(scenario):
    t = toy_tensor()
    res = evaluate(tensor=t, controller=StaticController(name="static"), scenario=scenario, seed=0,
                   limits={"id": None, "ood": None}, profile="demo", **RUN)
    tr = res.trajectories
    assert int(tr["id_day"]) == 3 and int(tr["ood_day"]) == 5 and str(tr["ood_label"]) == "d5"
    assert tr["id_pos"].shape == (144, scenario.n_uavs, 2) and tr["ood_status"].shape == (144, scenario.n_uavs)
    grid = Grid(rows=6, cols=6, cell_m=235.0)
    np.testing.assert_allclose(tr["id_pos"][0], initial_deployment(t, grid, scenario), atol=1e-3)
    # with the real battery, some UAVs must go and charge during a day (0.5..1.0 E_batt, ~101 kJ per slot)
    assert (tr["id_status"] == 2).any()


def test_batched_and_day_by_day_evaluation_agree_and_reruns_are_identical(make_scenario):
    scn = make_scenario(n_uavs=3, demand_intensity=150.0)
    t = toy_tensor(n_test=4)
    greedy = GreedyController(name="greedy", options=SearchSettings(sweeps=1, lattice=3, refine=0, bw_logits=()))
    runs = [evaluate(tensor=t, controller=greedy, scenario=scn, seed=1, limits={"id": None, "ood": 1}, profile="demo",
                     device="cpu", batch_days=b, progress_interval_s=5.0).days
            for b in (True, False, True)]
    cols = ["day", "sr_mean", "energy_kj_per_slot", "jain"]
    np.testing.assert_allclose(runs[0].select(cols).to_numpy(), runs[1].select(cols).to_numpy(), rtol=1e-5)
    assert runs[0].drop("plan_ms_per_slot").equals(runs[2].drop("plan_ms_per_slot"))


def test_split_summary_averages_days_of_each_split():
    df = pl.DataFrame({"split": ["id", "id", "ood"], "sr_mean": [0.5, 0.7, 0.9], "energy_kj_per_slot": [1.0, 3.0, 2.0],
                       "energy_efficiency": [1.0, 1.0, 1.0], "jain": [1.0, 0.5, 1.0],
                       "plan_ms_per_slot": [1.0, 1.0, 2.0], "stat_solves": [24.0, 10.0, None]})
    s = split_summary(df)
    assert s["id/sr_mean"] == pytest.approx(0.6) and s["ood/sr_mean"] == pytest.approx(0.9)
    assert s["id/energy_kj_per_slot"] == pytest.approx(2.0) and s["id/jain"] == pytest.approx(0.75)
    # a controller's per-day stats are averaged too; a split where it reported nothing is left out
    assert s["id/stat_solves"] == pytest.approx(17.0) and "ood/stat_solves" not in s


def test_a_writer_that_fails_midway_leaves_no_file_under_the_final_name(tmp_path):
    from prep.atomic import atomic_path, write_json

    target = tmp_path / "seed0" / "days.parquet"
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_bytes(b"half a file")
            raise RuntimeError("killed")
    assert not target.exists() and list(target.parent.iterdir()) == []
    write_json(tmp_path / "m.json", {"b": 1, "a": [2]})
    assert (tmp_path / "m.json").read_text() == '{\n  "a": [\n    2\n  ],\n  "b": 1\n}\n'


def static_method_record(name: str) -> dict:
    """A method record of a method that runs no search (what the evaluate job records for Static)."""
    return {"method": name, "class": "dswm.methods.classical:StaticController", "options": None, "search": None}


def test_days_file_carries_the_record_of_the_model_it_evaluated(tmp_path, monkeypatch):
    import json

    from dswm.protocol.evaluation import read_model_record, write_days
    from dswm.pipeline.setup import model_record
    from prep.rawio import sha256_file

    monkeypatch.chdir(tmp_path)
    run = tmp_path / "results/milan/dswm/seed0"
    run.mkdir(parents=True)
    (run / "model.pt").write_bytes(b"weights of dswm")
    (run / "train_manifest.json").write_text(json.dumps({"model_sha256": sha256_file(run / "model.pt")}))
    rec = model_record(method="dswm_wo_unc", source="dswm", model=run / "model.pt",
                       manifest=run / "train_manifest.json")
    assert rec == {"method": "dswm_wo_unc", "train_source": "dswm", "model": "results/milan/dswm/seed0/model.pt",
                   "model_sha256": sha256_file(run / "model.pt"),
                   "train_manifest": "results/milan/dswm/seed0/train_manifest.json"}
    days = pl.DataFrame({"day": [1, 2], "sr_mean": [0.5, 0.6]})
    write_days(days, tmp_path / "days.parquet", rec, static_method_record("dswm_wo_unc"))
    assert read_model_record(tmp_path / "days.parquet") == rec
    assert pl.read_parquet(tmp_path / "days.parquet").equals(days)  # the table itself is unchanged
    assert sorted(p.name for p in tmp_path.iterdir()) == ["days.parquet", "results"]  # no temp file left
    static = model_record(method="static")
    write_days(days, tmp_path / "static.parquet", static, static_method_record("static"))
    assert read_model_record(tmp_path / "static.parquet")["model"] is None
    days.write_parquet(tmp_path / "bare.parquet")
    assert read_model_record(tmp_path / "bare.parquet") is None


def test_a_model_that_is_not_the_one_its_manifest_recorded_is_refused(tmp_path, monkeypatch):
    """A truncated model.pt: refused before it is loaded, with the command that has its train job write it again."""
    import hashlib
    import json
    from pathlib import Path

    from dswm.pipeline.setup import model_record

    monkeypatch.chdir(tmp_path)  # the workflow's root: the command names the model as Snakemake does
    model = Path("results/milan/dswm/seed0/model.pt")
    model.parent.mkdir(parents=True)
    trained = b"the model dswm trained" * 100
    model.write_bytes(trained[: len(trained) // 2])
    manifest = model.parent / "train_manifest.json"
    manifest.write_text(json.dumps({"model_sha256": hashlib.sha256(trained).hexdigest()}))
    with pytest.raises(ValueError) as err:
        model_record(method="dswm_wo_unc", source="dswm", model=tmp_path / model, manifest=manifest)
    assert str(err.value) == (
        f"{tmp_path / model}: SHA-256 is {hashlib.sha256(model.read_bytes()).hexdigest()}, expected "
        f"{hashlib.sha256(trained).hexdigest()} (model_sha256 of {manifest}) — not the model dswm trained for "
        f"dswm_wo_unc; re-run the train job of dswm: `rm results/milan/dswm/seed0/model.pt`, then the same snakemake "
        f"command again (or add `--forcerun results/milan/dswm/seed0/model.pt` to it)")


def test_days_file_carries_the_resolved_settings_and_search_of_its_method(tmp_path):
    from dswm.config import to_plain
    from dswm.methods.base import Controller
    from dswm.pipeline.setup import method_record, model_record
    from dswm.protocol.evaluation import (METHOD_RECORD_FIELDS, read_method_record, read_model_record,
                                          write_days)
    from dswm.settings import MethodSettings

    search = SearchSettings(sweeps=3, lattice=7, refine=2, bw_logits=(1.0, -1.0, 0.0))

    class Searching(Controller):
        def search_settings(self):
            return search

    m = MethodSettings(name="greedy", target="dswm.methods.classical:GreedyController", label="Greedy",
                       table_class="heuristic", learns=False, training_source=None, options=search)
    rec = method_record(m, Searching(name="greedy"))
    assert rec == {"method": "greedy", "class": "dswm.methods.classical:GreedyController",
                   "options": to_plain(search), "search": {"sweeps": 3, "lattice": 7, "refine": 2,
                                                           "bw_logits": [0.0, 1.0, -1.0]}}
    days = pl.DataFrame({"day": [1, 2], "sr_mean": [0.5, 0.6]})
    path = tmp_path / "days.parquet"
    write_days(days, path, model_record(method="greedy"), rec)
    assert read_method_record(path) == rec  # round trip: plain JSON in, the same plain JSON out
    assert read_model_record(path)["method"] == "greedy"  # both records, side by side
    assert pl.read_parquet(path).equals(days)
    static = method_record(dataclasses.replace(m, name="static", target="dswm.methods.classical:StaticController",
                                                options=None), Controller(name="static"))
    assert static == static_method_record("static")  # a method that runs no search records search null
    write_days(days, tmp_path / "static.parquet", model_record(method="static"), static)
    assert read_method_record(tmp_path / "static.parquet")["search"] is None
    days.write_parquet(tmp_path / "bare.parquet")
    assert read_method_record(tmp_path / "bare.parquet") is None
    for field in METHOD_RECORD_FIELDS:
        bad = {k: v for k, v in rec.items() if k != field}
        with pytest.raises(ValueError, match=rf"method record lacks \['{field}'\]"):
            write_days(days, tmp_path / "bad.parquet", model_record(method="greedy"), bad)
    with pytest.raises(ValueError, match="class = 'GreedyController'"):
        write_days(days, tmp_path / "bad.parquet", model_record(method="greedy"), {**rec, "class": "GreedyController"})
    with pytest.raises(ValueError, match="search = 3"):
        write_days(days, tmp_path / "bad.parquet", model_record(method="greedy"), {**rec, "search": 3})
    with pytest.raises(ValueError, match="model record lacks"):
        write_days(days, tmp_path / "bad.parquet", {"method": "greedy"}, rec)
    assert not (tmp_path / "bad.parquet").exists()  # a refused record writes nothing
