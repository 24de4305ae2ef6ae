"""Tables from result files: numbers worked out by hand, fixed CSV columns, row order, provenance line."""
import csv
import json
import shutil
from pathlib import Path

import polars as pl
import pytest

from dswm.methods.registry import BUILTIN
from dswm.protocol.tables import CROSS_COLUMNS, MAIN_COLUMNS, ROOM_COLUMNS, build_tables

TABLES = {"main_dataset": "milan", "decimals": 3, "split_labels": {"id": "Weekday", "ood": "Holiday"},
          "class_order": ["world model", "model-free", "deployment", "upper bound"],
          "room": {"low": "static", "high": "oracle", "fill": ["greedy"], "min_room": 0.168, "ladder": []}}

# (dataset, method, seed) -> ({ID day: SR}, {OOD day: SR})
SCORES = {
    ("milan", "static", 0): ({0: 0.70, 1: 0.74}, {3: 0.75, 4: 0.77}),
    ("milan", "static", 1): ({0: 0.72, 1: 0.76}, {3: 0.75, 4: 0.79}),
    ("milan", "greedy", 0): ({0: 0.80, 1: 0.82}, {3: 0.85, 4: 0.85}),
    ("milan", "greedy", 1): ({0: 0.78, 1: 0.80}, {3: 0.81, 4: 0.83}),
    ("milan", "oracle", 0): ({0: 0.90, 1: 0.90}, {3: 0.92, 4: 0.94}),
    ("milan", "oracle", 1): ({0: 0.90, 1: 0.90}, {3: 0.92, 4: 0.94}),
    ("shanghai", "static", 0): ({5: 0.40}, {7: 0.45}),
    ("shanghai", "greedy", 0): ({5: 0.60}, {7: 0.62}),
    ("shanghai", "oracle", 0): ({5: 0.70}, {7: 0.71}),
}


def write_results(root, profile="demo"):
    paths = []
    for (ds, method, seed), (id_days, ood_days) in SCORES.items():
        rows = [{"day": d, "split": s, "sr_mean": v} for s, days in (("id", id_days), ("ood", ood_days))
                for d, v in days.items()]
        df = pl.DataFrame(rows).with_columns(pl.lit(ds).alias("dataset"), pl.lit(method).alias("method"),
                                             pl.lit(seed).alias("seed"), pl.lit(profile).alias("profile"),
                                             pl.lit("d").alias("label"), pl.lit(1.0).alias("jain"),
                                             (1000.0 + 100.0 * pl.col("sr_mean")).alias("energy_kj_per_slot"),
                                             (pl.col("sr_mean") / 2).alias("energy_efficiency"))
        p = root / ds / method / f"seed{seed}" / "days.parquet"
        p.parent.mkdir(parents=True)
        df.write_parquet(p)
        paths.append(p)
    metas = {}
    for ds, source in (("milan", "demo"), ("shanghai", "raw")):
        metas[ds] = root / f"{ds}_meta.json"
        metas[ds].write_text(json.dumps({"dataset": ds, "source": source}))
    return paths, metas


def build(tmp_path, profile="demo", results_profile="demo"):
    paths, metas = write_results(tmp_path / "results", results_profile)
    specs = {m: BUILTIN[m] for m in ("static", "greedy", "oracle")}
    return build_tables(result_paths=paths, meta_paths=metas, specs=specs, run_order=["static", "greedy", "oracle"],
                        tables_cfg=TABLES, profile=profile, out_dir=tmp_path / "tables")


def read_csv(path):
    with open(path) as fh:
        return list(csv.DictReader(fh))


def test_main_table_numbers_by_hand(tmp_path):
    build(tmp_path)
    rows = read_csv(tmp_path / "tables" / "milan_main.csv")
    assert list(rows[0]) == MAIN_COLUMNS
    # grouped by class: model-free (greedy), deployment (static), upper bound (oracle)
    assert [(r["method"], r["class"]) for r in rows] == [("greedy", "model-free"), ("static", "deployment"),
                                                         ("oracle", "upper bound")]
    static = rows[1]
    # seed scores: weekday 0.72 and 0.74 -> mean 0.73, sample std 0.01*sqrt(2) = 0.0141421
    assert float(static["weekday_mean"]) == pytest.approx(0.73)
    assert float(static["weekday_std"]) == pytest.approx(0.0141421356, abs=1e-9)
    # holiday: 0.76 and 0.77 -> 0.765, std 0.00707107
    assert float(static["holiday_mean"]) == pytest.approx(0.765)
    assert float(static["holiday_std"]) == pytest.approx(0.00707106781, abs=1e-9)
    assert static["n_seeds"] == "2"
    greedy = rows[0]  # weekday 0.81 / 0.79; holiday 0.85 / 0.82
    assert float(greedy["weekday_mean"]) == pytest.approx(0.80)
    assert float(greedy["holiday_mean"]) == pytest.approx(0.835)
    assert float(rows[2]["weekday_std"]) == 0.0
    # Table III (b), (c) and fairness: energy = 1000 + 100 SR, efficiency = SR / 2 per day, as the served ratio
    assert float(static["energy_weekday_mean"]) == pytest.approx(1073.0)
    assert float(static["energy_weekday_std"]) == pytest.approx(1.41421356, abs=1e-6)
    assert float(static["efficiency_holiday_mean"]) == pytest.approx(0.3825)
    assert float(static["jain_weekday_mean"]) == 1.0


def test_cross_table_one_row_per_method_and_dataset(tmp_path):
    build(tmp_path)
    rows = read_csv(tmp_path / "tables" / "cross_dataset.csv")
    assert list(rows[0]) == CROSS_COLUMNS
    assert [(r["method"], r["dataset"]) for r in rows] == [(m, d) for m in ("greedy", "static", "oracle")
                                                           for d in ("milan", "shanghai")]
    sh_static = next(r for r in rows if (r["method"], r["dataset"]) == ("static", "shanghai"))
    assert (float(sh_static["weekday_mean"]), float(sh_static["holiday_mean"]), sh_static["n_seeds"]) == \
        (pytest.approx(0.40), pytest.approx(0.45), "1")
    md = (tmp_path / "tables" / "cross_dataset.md").read_text()
    assert "| Static (K-means) | 0.730/0.765 | 0.400/0.450 |" in md


def test_tables_state_the_profile_and_where_the_data_came_from(tmp_path):
    build(tmp_path)
    for name in ("milan_main", "cross_dataset"):
        for ext in ("md", "tex"):
            text = (tmp_path / "tables" / f"{name}.{ext}").read_text()
            assert "profile: demo" in text and "Milan: demo" in text and "Shanghai: raw" in text
    md = (tmp_path / "tables" / "milan_main.md").read_text()
    # energy 1000 + 100 SR per day: weekday seed means 1072 and 1074; efficiency SR/2; Jain 1 on every day
    assert ("| Static (K-means) | deployment | 0.730±0.014 | 0.765±0.007 | 1073.0±1.4 | 1076.5±0.7 | 0.365±0.007 | "
            "0.383±0.004 | 1.000±0.000 | 1.000±0.000 | 2 |") in md
    tex = (tmp_path / "tables" / "milan_main.tex").read_text()
    assert r"0.730$\pm$0.014" in tex and r"\toprule" in tex and r"\label{tab:milan}" in tex


def test_room_footnote_by_hand(tmp_path):
    build(tmp_path)
    rows = read_csv(tmp_path / "tables" / "room.csv")
    assert list(rows[0]) == ROOM_COLUMNS
    got = {(r["dataset"], r["split"]): r for r in rows}
    assert sorted(got) == [("milan", "holiday"), ("milan", "weekday"), ("shanghai", "holiday"), ("shanghai", "weekday")]
    # Milan weekday: static 0.73 -> oracle 0.90, room 0.17; greedy 0.80 fills 0.07 / 0.17
    mw = got[("milan", "weekday")]
    assert float(mw["room"]) == pytest.approx(0.17) and float(mw["filled"]) == pytest.approx(0.07 / 0.17)
    # Shanghai holiday: 0.45 -> 0.71, greedy 0.62 fills 0.17 / 0.26
    assert float(got[("shanghai", "holiday")]["filled"]) == pytest.approx(0.17 / 0.26)
    main = (tmp_path / "tables" / "milan_main.md").read_text()
    assert "Static (K-means) -> Oracle (clairvoyant)" in main
    assert "Milan Weekday 0.730 -> 0.900 (room +0.170; gained: Greedy (BCD) +0.070 (41%))" in main
    assert "Shanghai Weekday" not in main                  # the main table speaks of its dataset only
    cross = (tmp_path / "tables" / "cross_dataset.md").read_text()
    assert "Shanghai Holiday 0.450 -> 0.710 (room +0.260; gained: Greedy (BCD) +0.170 (65%))" in cross
    # Milan holiday's room, 0.93 - 0.765 = 0.165, is below min_room 0.168: its gain is given, not a share
    assert got[("milan", "holiday")]["filled"] == ""
    assert "Milan Holiday 0.765 -> 0.930 (room +0.165; gained: Greedy (BCD) +0.070)" in main
    assert r"41\%" in (tmp_path / "tables" / "milan_main.tex").read_text()


def test_the_ladder_of_bounds_by_hand_with_a_ceiling_that_flies_no_fleet(tmp_path):
    """tables.room.ladder: per dataset and split, room.csv gives each rung (its position in `rung`) beside the fill
    methods, and both footnotes give the ladder; the ceiling's row shows no energy ("--"): it flies no fleet."""
    paths, metas = write_results(tmp_path / "results")
    ceiling = {("milan", 0): ({0: 0.95, 1: 0.97}, {3: 0.98, 4: 0.98}),
               ("milan", 1): ({0: 0.95, 1: 0.97}, {3: 0.98, 4: 0.98}), ("shanghai", 0): ({5: 0.90}, {7: 0.93})}
    for (ds, seed), (id_days, ood_days) in ceiling.items():
        rows = [{"day": d, "split": s, "sr_mean": v} for s, days in (("id", id_days), ("ood", ood_days))
                for d, v in days.items()]
        p = tmp_path / "results" / ds / "ceiling" / f"seed{seed}" / "days.parquet"
        p.parent.mkdir(parents=True)
        pl.DataFrame(rows).with_columns(
            pl.lit(ds).alias("dataset"), pl.lit("ceiling").alias("method"), pl.lit(seed).alias("seed"),
            pl.lit("demo").alias("profile"), pl.lit("d").alias("label"), pl.lit(1.0).alias("jain"),
            pl.lit(None, pl.Float64).alias("energy_kj_per_slot"),
            pl.lit(None, pl.Float64).alias("energy_efficiency")).write_parquet(p)
        paths.append(p)
    run_order = ["static", "greedy", "oracle", "ceiling"]
    tables = {**TABLES, "room": {**TABLES["room"], "ladder": ["static", "greedy", "oracle", "ceiling"]}}
    build_tables(result_paths=paths, meta_paths=metas, specs={m: BUILTIN[m] for m in run_order}, run_order=run_order,
                 tables_cfg=tables, profile="demo", out_dir=tmp_path / "tables")
    rows = read_csv(tmp_path / "tables" / "room.csv")
    assert list(rows[0]) == ROOM_COLUMNS
    mw = [r for r in rows if (r["dataset"], r["split"]) == ("milan", "weekday")]
    # the rungs in ladder order; greedy, the fill method, is a rung here, so it is not repeated
    assert [(r["method"], r["rung"]) for r in mw] == [("static", "0"), ("greedy", "1"), ("oracle", "2"),
                                                      ("ceiling", "3")]
    assert [float(r["method_mean"]) for r in mw] == pytest.approx([0.73, 0.80, 0.90, 0.96])
    # the ceiling fills (0.96 - 0.73) / 0.17 of the room from static to the oracle
    assert float(mw[3]["filled"]) == pytest.approx(0.23 / 0.17)
    main = (tmp_path / "tables" / "milan_main.md").read_text()
    assert ("Ladder of references and bounds, Static (K-means) -> Greedy (BCD) -> Oracle (clairvoyant) -> Ceiling "
            "(clairvoyant): Milan Weekday 0.730 -> 0.800 -> 0.900 -> 0.960; Milan Holiday 0.765 -> 0.835 -> 0.930 -> "
            "0.980.") in main
    assert "Milan Weekday 0.730 -> 0.900 (room +0.170; gained: Greedy (BCD) +0.070 (41%))" in main  # the room note
    assert ("| Ceiling (clairvoyant) | upper bound | 0.960±0.000 | 0.980±0.000 | -- | -- | -- | -- | 1.000±0.000 | "
            "1.000±0.000 | 2 |") in main
    cross = (tmp_path / "tables" / "cross_dataset.md").read_text()
    assert "Shanghai Weekday 0.400 -> 0.600 -> 0.700 -> 0.900; Shanghai Holiday 0.450 -> 0.620 -> 0.710 -> 0.930." \
        in cross
    assert "| Ceiling (clairvoyant) | 0.960/0.980 | 0.900/0.930 |" in cross


def test_results_of_another_profile_are_refused(tmp_path):
    with pytest.raises(ValueError, match="profile 'smoke'"):
        build(tmp_path, profile="demo", results_profile="smoke")


def test_a_seed_missing_one_split_is_refused(tmp_path):
    paths, metas = write_results(tmp_path / "results")
    p = tmp_path / "results" / "milan" / "greedy" / "seed1" / "days.parquet"
    pl.read_parquet(p).filter(pl.col("split") == "id").write_parquet(p)
    with pytest.raises(ValueError, match="milan/greedy"):
        build_tables(result_paths=paths, meta_paths=metas, specs=BUILTIN, run_order=["static", "greedy", "oracle"],
                     tables_cfg=TABLES, profile="demo", out_dir=tmp_path / "tables")


def test_the_main_table_follows_tables_main_dataset(tmp_path):
    paths, metas = write_results(tmp_path / "results")
    specs = {m: BUILTIN[m] for m in ("static", "greedy", "oracle")}
    frames = build_tables(result_paths=paths, meta_paths=metas, specs=specs, run_order=["static", "greedy", "oracle"],
                          tables_cfg={**TABLES, "main_dataset": "shanghai"}, profile="demo",
                          out_dir=tmp_path / "tables")
    assert sorted(frames) == ["cross_dataset", "shanghai_main"]
    rows = read_csv(tmp_path / "tables" / "shanghai_main.csv")
    assert {r["method"]: (float(r["weekday_mean"]), float(r["holiday_mean"])) for r in rows} == {
        "static": (0.40, 0.45), "greedy": (0.60, 0.62), "oracle": (0.70, 0.71)}
    assert r"\label{tab:shanghai}" in (tmp_path / "tables" / "shanghai_main.tex").read_text()
    assert not (tmp_path / "tables" / "milan_main.csv").exists()
    with pytest.raises(ValueError, match=r"'tables.main_dataset' is 'yjmob', which this run does not evaluate"):
        build_tables(result_paths=paths, meta_paths=metas, specs=specs, run_order=["static", "greedy", "oracle"],
                     tables_cfg={**TABLES, "main_dataset": "yjmob"}, profile="demo", out_dir=tmp_path / "t2")


def test_results_database_views_are_the_days_and_the_tables_numbers(tmp_path, monkeypatch):
    """results.duckdb: `days` reads every result file in place (no copy), `summary` holds the tables' numbers, and the
    stored paths are relative to the working directory, so a moved copy of the tree still answers."""
    import duckdb

    monkeypatch.chdir(tmp_path)
    paths, metas = write_results(Path("results"))
    specs = {m: BUILTIN[m] for m in ("static", "greedy", "oracle")}
    build_tables(result_paths=paths, meta_paths=metas, specs=specs, run_order=["static", "greedy", "oracle"],
                 tables_cfg=TABLES, profile="demo", out_dir=Path("results/tables"), database="results/results.duckdb")
    assert sorted(p.name for p in Path("results").iterdir() if p.is_file()) == [  # no temp or WAL file left
        "milan_meta.json", "results.duckdb", "shanghai_meta.json"]
    moved = tmp_path.parent / f"{tmp_path.name}-moved"
    shutil.copytree(tmp_path, moved)
    shutil.rmtree(tmp_path / "results")
    monkeypatch.chdir(moved)
    con = duckdb.connect("results/results.duckdb", read_only=True)
    n_days = sum(len(i) + len(o) for i, o in SCORES.values())
    assert con.sql("SELECT count(*) FROM days").fetchall() == [(n_days,)] == [(30,)]
    assert con.sql("SELECT count(*) FROM duckdb_tables()").fetchall() == [(0,)]  # views only: the data stays in Parquet
    assert con.sql("SELECT sr_mean FROM days WHERE dataset = 'shanghai' AND method = 'greedy' AND split = 'ood'"
                   ).fetchall() == [(0.62,)]
    summary = {(r[0], r[1]): r for r in con.sql("SELECT dataset, method, weekday_mean, weekday_std, holiday_mean, "
                                                "holiday_std, n_seeds, energy_weekday_mean, jain_holiday_std "
                                                "FROM summary").fetchall()}
    for row in read_csv(moved / "results/tables/cross_dataset.csv"):  # equal to the last bit, as the CSV writes it
        got = summary[(row["dataset"], row["method"])]
        assert [repr(v) for v in got[2:6]] == [row[k] for k in ("weekday_mean", "weekday_std", "holiday_mean",
                                                                "holiday_std")]
        assert str(got[6]) == row["n_seeds"]
    for row in read_csv(moved / "results/tables/milan_main.csv"):
        got = summary[("milan", row["method"])]
        assert (repr(got[7]), repr(got[8])) == (row["energy_weekday_mean"], row["jain_holiday_std"])
    assert summary[("milan", "static")][2] == pytest.approx(0.73)
