"""The figures of where foresight pays: the foresight grid (demand source x planner) and the headroom map (D_max x u): which extra
runs they need, the settings each run changes, and the numbers of their tables."""
import polars as pl
import pytest
import yaml

from conftest import ROOT
from dswm import settings as S
from dswm.figures.common import read_csv
from dswm.figures.foresight import draw_foresight, foresight_table
from dswm.figures.headroom import draw_headroom, headroom_table


def _settings(profile):
    config = yaml.safe_load((ROOT / "config.yaml").read_text())
    config["profile"] = profile
    return S.resolve(config)


@pytest.fixture(scope="module")
def demo():
    return _settings("demo")


# ---- the runs ----------------------------------------------------------------------------------------------
def test_composite_variant_names_parse_back_and_refuse_bad_changes():
    v = S.parse_variant("D250u0.5")
    assert (v.kind, v.value, v.more, v.name) == ("D", 250.0, (("u", 0.5),), "D250u0.5")
    assert v.get("u") == 0.5 and v.get("K") is None
    assert S.parse_variant("rho0").value == 0.0 and S.parse_variant("alg1").name == "alg1"
    for bad, match in (("alg2", "alg1"), ("rho1.5", r"rho<r> in \[0, 1\]"), ("D0", "D<metres> > 0"),
                       ("u2u3", "appears twice"), ("D250x", "do<s>, K<integer> or u<factor>")):
        with pytest.raises(ValueError, match=match):
            S.parse_variant(bad)


def test_the_grid_reuses_the_methods_own_cells_and_adds_four_runs(demo):
    cells = S.foresight_cells(demo, "milan")
    got = [(c["planner"], c["source"], c["rho"], c["method"], c["variant"] and c["variant"].name) for c in cells]
    assert got == [("alg1", "persistence", None, "dswm_plus_persist", "alg1"),
                   ("alg1", "model", 0.95, "dswm", None),
                   ("alg1", "model", 0.0, "dswm", "rho0"),
                   ("alg1", "true", None, "perfect", "alg1"),
                   ("plus", "persistence", None, "dswm_plus_persist", None),
                   ("plus", "model", 0.95, "dswm_plus", None),
                   ("plus", "model", 0.0, "dswm_plus", "rho0"),
                   ("plus", "true", None, "perfect", None)]
    jobs = S.foresight_jobs(demo)
    assert len(jobs) == 4 * 3 and ("yjmob", "alg1", "perfect", 0) in jobs     # 4 runs x 3 datasets, seed 0


def test_algorithm_1_on_given_maps_takes_dswms_whole_planner_and_rho_0_trains_nothing(demo):
    alg = S.variant_evaluate_slice(demo, "perfect", S.parse_variant("alg1"))
    assert alg["method"]["options"]["planner"] == S.evaluate_slice(demo, "dswm")["method"]["options"]["planner"]
    assert alg["method"]["target"] == S.evaluate_slice(demo, "perfect")["method"]["target"]   # still the true maps
    assert alg["eval_days"] == {"id": 1, "ood": 0}                              # figures.budgets.demo.foresight
    rho0 = S.variant_evaluate_slice(demo, "dswm_plus", S.parse_variant("rho0"))
    assert rho0["method"]["options"]["planner"]["rho"] == 0.0
    assert rho0["method"]["options"]["planner"]["proposal"] == "bcd"           # DSWM+'s planner otherwise
    assert not S.variant_retrains(demo, "dswm_plus", S.parse_variant("rho0"))  # the main train job's model
    assert not S.variant_retrains(demo, "dswm", S.parse_variant("rho0"))


def test_the_headroom_map_runs_greedy_and_perfect_per_cell_and_the_ceiling_once_per_factor(demo):
    jobs = S.headroom_jobs(demo)
    # the demo's map, D_max 250 and 1500 m, u x 1 and x 2: 2 datasets x (2 methods x (2 x 2 - 1) cells + the ceiling
    # at u x 2), seed 0
    assert len(jobs) == 2 * (2 * 3 + 1)
    assert not [j for j in jobs if j[1].startswith(("D500", "D1000"))]
    assert not [j for j in jobs if "u0.5" in j[1]]
    paper = S.headroom_jobs(_settings("paper"))  # all three intensities: Milan 5 seeds, Shanghai 3
    assert len(paper) == (5 + 3) * (2 * 11 + 2) and ("milan", "D250u0.5", "perfect", 4) in paper
    assert ("shanghai", "D1500u2", "ceiling", 0) in jobs and ("milan", "D250", "perfect", 0) in jobs
    assert not [j for j in jobs if j[2] == "ceiling" and not j[1].startswith("D1500")]
    assert S.headroom_variant(demo, 1500.0, 1.0) is None                        # the main evaluation
    ev = S.variant_evaluate_slice(demo, "greedy", S.parse_variant("D250u2"))
    assert ev["scenario"]["d_max_m"] == 250.0 and ev["intensity_scale"] == 2.0
    assert ev["eval_days"] == {"id": 1, "ood": 0}                               # figures.budgets.demo.headroom
    assert S.variant_evaluate_slice(demo, "greedy", S.parse_variant("u2"))["eval_days"] == {"id": 2, "ood": 0}
    names = {v.name for v in S.figure_variants(demo)}
    assert {"do0.5", "K8", "u2", "rho0", "alg1", "D250u2", "D1500u2"} <= names and "D250u0.5" not in names


def test_a_bad_headroom_grid_is_refused_by_the_schema():
    config = yaml.safe_load((ROOT / "config.yaml").read_text())
    config["figures"]["headroom"]["d_max_m"] = [0.0, 500.0]
    with pytest.raises(S.ConfigError, match=r"figures\.headroom\.d_max_m"):
        S.resolve(config)


# ---- the tables ----------------------------------------------------------------------------------------------
def _rows(dataset, method, srs, *, seed=0, days=(10, 11), variant=None):
    frame = pl.DataFrame({"dataset": dataset, "method": method, "seed": seed, "split": "id", "day": list(days),
                          "sr_mean": list(srs)}, schema_overrides={"seed": pl.Int32, "day": pl.Int32})
    return frame if variant is None else frame.with_columns(pl.lit(variant).alias("variant"))


def _cells():
    cells = []
    for planner, methods in (("alg1", ("dswm_plus_persist", "dswm", "dswm", "perfect")),
                             ("plus", ("dswm_plus_persist", "dswm_plus", "dswm_plus", "perfect"))):
        for (source, rho), method in zip((("persistence", None), ("model", 0.95), ("model", 0.0), ("true", None)),
                                         methods):
            variant = {"alg1": "alg1"}.get(planner) if method in ("dswm_plus_persist", "perfect") else None
            if rho == 0.0:
                variant = "rho0"
            cells.append({"planner": planner, "source": source, "rho": rho, "method": method, "variant": variant})
    return cells


def test_foresight_table_cuts_the_main_files_to_the_grids_days_and_gives_the_share_of_the_room(tmp_path):
    main = pl.concat([_rows("milan", "greedy", [0.70, 0.80, 0.0], days=(10, 11, 12)),   # day 12 is cut
                      _rows("milan", "perfect", [0.80, 0.90, 0.0], days=(10, 11, 12)),
                      _rows("milan", "dswm", [0.60, 0.70, 0.0], days=(10, 11, 12)),
                      _rows("milan", "dswm_plus", [0.76, 0.84, 0.0], days=(10, 11, 12)),
                      _rows("milan", "dswm_plus_persist", [0.75, 0.83, 0.0], days=(10, 11, 12))])
    runs = pl.concat([_rows("milan", "dswm_plus_persist", [0.65, 0.75], variant="alg1"),
                      _rows("milan", "perfect", [0.66, 0.76], variant="alg1"),
                      _rows("milan", "dswm", [0.62, 0.72], variant="rho0"),
                      _rows("milan", "dswm_plus", [0.74, 0.82], variant="rho0")])
    cells = _cells()
    cells[3] = {**cells[3], "method": None, "variant": None}                    # a cell the profile does not run
    table = foresight_table(main, runs, {"milan": cells}, seeds={"milan": [0]}, limits=S.EvalDayLimits(id=2, ood=0))
    get = {(r["planner"], r["source"], r["rho"]): r for r in table.iter_rows(named=True)}
    assert get[("reference", "greedy", None)]["sr_mean"] == pytest.approx(0.75)
    assert get[("reference", "perfect", None)]["sr_mean"] == pytest.approx(0.85)
    plus = get[("plus", "model", 0.95)]
    assert plus["status"] == "main" and plus["sr_mean"] == pytest.approx(0.80) and plus["days"] == 2
    assert plus["share_of_room"] == pytest.approx(0.5)                         # (0.80 - 0.75) / (0.85 - 0.75)
    assert get[("alg1", "model", 0.0)]["sr_mean"] == pytest.approx(0.67)
    assert get[("alg1", "model", 0.0)]["vs_greedy"] == pytest.approx(-0.08)
    assert get[("alg1", "persistence", None)]["status"] == "extra"
    assert get[("alg1", "true", None)]["status"] == "not run" and get[("alg1", "true", None)]["sr_mean"] is None
    assert get[("alg1", "true", None)]["note"].startswith("not run: the profile does not evaluate")
    assert get[("plus", "true", None)]["note"].startswith("given maps: no anchoring (rho does not apply)")
    assert get[("plus", "model", 0.0)]["note"] is None
    out = {k: tmp_path / f"foresight.{k}" for k in ("png", "pdf", "csv")}
    draw_foresight(table, {}, dataset_labels={"milan": "Milan"}, profile="smoke", source="demo", out=out)
    csv = read_csv(out["csv"])
    assert csv.filter(pl.col("status") == "not run").height == 1 and out["png"].stat().st_size > 0


def test_foresight_table_refuses_a_run_on_other_days():
    main = pl.concat([_rows("milan", m, [0.7, 0.8]) for m in ("greedy", "perfect", "dswm", "dswm_plus",
                                                               "dswm_plus_persist")])
    runs = pl.concat([_rows("milan", "dswm", [0.6], days=(13,), variant="rho0")])
    cells = [{"planner": "alg1", "source": "model", "rho": 0.0, "method": "dswm", "variant": "rho0"}]
    with pytest.raises(ValueError, match="foresight milan rho0/dswm.*same days"):
        foresight_table(main, runs, {"milan": cells}, seeds={"milan": [0]}, limits=S.EvalDayLimits(id=2, ood=0))


def test_headroom_table_gives_room_and_motion_cost_and_names_the_regimes(tmp_path):
    own = 1500.0
    names = {(d, f): (None if (d, f) == (own, 1.0) else f"D{d:g}" + ("" if f == 1.0 else f"u{f:g}"))
             for d in (250.0, own) for f in (1.0, 2.0)}
    main = pl.concat([_rows("milan", "greedy", [0.80, 0.90]), _rows("milan", "perfect", [0.81, 0.91]),
                      _rows("milan", "ceiling", [0.90, 0.96])])
    runs = pl.concat([_rows("milan", "greedy", [0.60, 0.70], variant="D250"),
                      _rows("milan", "perfect", [0.64, 0.74], variant="D250"),
                      _rows("milan", "greedy", [0.50, 0.60], variant="D250u2"),
                      _rows("milan", "perfect", [0.51, 0.61], variant="D250u2"),
                      _rows("milan", "greedy", [0.70, 0.80], variant="D1500u2"),
                      _rows("milan", "perfect", [0.72, 0.80], variant="D1500u2"),
                      _rows("milan", "ceiling", [0.85, 0.85], variant="D1500u2")])
    table = headroom_table(main, runs, datasets=["milan"], d_max_m=[250.0, own], intensity_scales=[1.0, 2.0],
                           own_d_max=own, seeds={"milan": [0]}, limits=S.EvalDayLimits(id=2, ood=0),
                           min_room=0.02, names=names)
    get = {(r["d_max_m"], r["factor"]): r for r in table.iter_rows(named=True)}
    assert get[(own, 1.0)]["room"] == pytest.approx(0.01) and get[(own, 1.0)]["motion_cost"] == pytest.approx(0.07)
    slow = get[(250.0, 1.0)]
    assert slow["room"] == pytest.approx(0.04) and slow["motion_cost"] == pytest.approx(0.93 - 0.69)
    assert slow["ceiling"] == pytest.approx(0.93)                              # the ceiling does not depend on D_max
    assert slow["share_ceiling_room"] == pytest.approx(0.04 / (0.93 - 0.65))
    assert get[(own, 2.0)]["room"] == pytest.approx(0.01) and get[(250.0, 2.0)]["ceiling"] == pytest.approx(0.85)
    assert table.filter(pl.col("named"))["regime"].to_list() == ["milan, D_max 250 m, u x 1"]
    out = {k: tmp_path / f"headroom.{k}" for k in ("png", "pdf", "csv")}
    draw_headroom(table, min_room=0.02, dataset_labels={"milan": "Milan"}, profile="smoke", source="demo", out=out)
    first = out["csv"].read_text().splitlines()[0]
    assert "Room >= 0.02 in: milan, D_max 250 m, u x 1." in first
    assert read_csv(out["csv"]).height == 4


def test_headroom_table_names_the_missing_run():
    main = pl.concat([_rows("milan", m, [0.8, 0.9]) for m in ("greedy", "perfect")])
    with pytest.raises(ValueError, match="no extra run D250 of greedy on milan"):
        headroom_table(main, None, datasets=["milan"], d_max_m=[250.0], intensity_scales=[1.0], own_d_max=1500.0,
                       seeds={"milan": [0]}, limits=S.EvalDayLimits(id=2, ood=0), min_room=0.02,
                       names={(250.0, 1.0): "D250", (1500.0, 1.0): None})
