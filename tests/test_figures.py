"""Figures of the results and the data: the numbers each draws (its CSV) worked out by hand, the three files."""
import os
import stat

import polars as pl
import pytest

from dswm.figures import common, eda, results

LABELS = {"dswm": "DSWM", "greedy": "Greedy", "static": "Static"}
CLASSES = {"dswm": "world model", "greedy": "model-free", "static": "deployment"}
KW = dict(labels=LABELS, classes=CLASSES, run_order=["static", "greedy", "dswm"],
          class_order=["world model", "model-free", "deployment"], split_labels={"id": "Weekday", "ood": "Holiday"},
          profile="smoke")


def day_rows():
    """Milan: 2 seeds x (2 ID days + 1 OOD day) per method; Shanghai: dswm and greedy, 1 seed. SR by hand."""
    sr = {("dswm", 0): [0.80, 0.82, 0.90], ("dswm", 1): [0.78, 0.80, 0.86],
          ("greedy", 0): [0.70, 0.72, 0.75], ("greedy", 1): [0.70, 0.72, 0.75],
          ("static", 0): [0.60, 0.60, 0.50], ("static", 1): [0.62, 0.62, 0.52]}
    rows = []
    for (m, seed), values in sr.items():
        for day, split, v in zip((10, 11, 13), ("id", "id", "ood"), values):
            rows.append({"dataset": "milan", "method": m, "seed": seed, "day": day, "label": f"d{day}",
                         "split": split, "sr_mean": v, "energy_kj_per_slot": 1200.0 + 10 * v,
                         "energy_efficiency": v / 2})
    for m, (wk, hd) in {"dswm": (0.5, 0.6), "greedy": (0.4, 0.45)}.items():
        rows += [{"dataset": "shanghai", "method": m, "seed": 0, "day": 3, "label": "d3", "split": "id",
                  "sr_mean": wk, "energy_kj_per_slot": 1200.0, "energy_efficiency": wk / 2},
                 {"dataset": "shanghai", "method": m, "seed": 0, "day": 5, "label": "d5", "split": "ood",
                  "sr_mean": hd, "energy_kj_per_slot": 1200.0, "energy_efficiency": hd / 2}]
    return pl.DataFrame(rows)


def test_save_figure_writes_png_pdf_and_the_data_with_its_caption(tmp_path):
    fig, ax = common.plt.subplots()
    ax.plot([0, 1], [1, 2])
    out = common.outputs(tmp_path / "figures" / "toy")
    common.save_figure(fig, pl.DataFrame({"x": [0, 1], "y": [1.0, 2.0]}), **out, profile="smoke", source="demo",
                       caption="Paper Fig. 0 (toy): a line.")
    assert out["png"].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out["pdf"].read_bytes()[:5] == b"%PDF-"
    assert out["csv"].read_text().splitlines()[0] == "# Paper Fig. 0 (toy): a line. (profile: smoke)"
    assert common.read_csv(out["csv"])["y"].to_list() == [1.0, 2.0]
    assert sorted(p.name for p in out["png"].parent.iterdir()) == ["toy.csv", "toy.pdf", "toy.png"]  # no temp left


def test_figure_files_get_the_usual_permissions_and_a_failed_write_leaves_nothing(tmp_path):
    """The figure files go through prep.atomic: umask permissions (not mkstemp's 0600) and no temp file left."""
    mask = os.umask(0o022)
    try:
        fig, _ = common.plt.subplots()
        out = common.outputs(tmp_path / "toy")
        common.save_figure(fig, pl.DataFrame({"x": [0]}), **out, profile="smoke", source="demo", caption="c")
    finally:
        os.umask(mask)
    assert {k: stat.S_IMODE(p.stat().st_mode) for k, p in out.items()} == {"png": 0o644, "pdf": 0o644, "csv": 0o644}
    fig, _ = common.plt.subplots()
    bad = common.outputs(tmp_path / "bad")
    with pytest.raises(AttributeError, match="write_csv"):       # the CSV fails after the PNG and the PDF
        common.save_figure(fig, None, **bad, profile="smoke", source="demo", caption="c")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.pdf", "bad.png", "toy.csv", "toy.pdf", "toy.png"]


def test_main_figure_numbers_are_seed_means_and_sample_stds(tmp_path):
    data = results.draw_main(day_rows(), dataset="milan", source="demo", out=common.outputs(tmp_path / "main"), **KW)
    # class order: world model (dswm), model-free (greedy), deployment (static)
    assert data["method"].unique(maintain_order=True).to_list() == ["dswm", "greedy", "static"]
    dswm_id = data.filter((pl.col("method") == "dswm") & (pl.col("split") == "id")).row(0, named=True)
    # seed means 0.81 and 0.79: mean 0.80, sample std 0.01*sqrt(2)
    assert dswm_id["sr_mean"] == pytest.approx(0.80)
    assert dswm_id["sr_mean_std"] == pytest.approx(0.0141421356, abs=1e-9)
    assert dswm_id["energy_kj_per_slot"] == pytest.approx(1208.0)
    assert dswm_id["energy_efficiency"] == pytest.approx(0.40)
    assert dswm_id["seeds"] == 2
    assert common.read_csv(tmp_path / "main.csv").height == 6  # 3 methods x 2 splits


def test_main_figure_draws_a_bound_without_energy_and_leaves_its_energy_empty(tmp_path):
    """The per-slot ceiling flies no fleet: its result files hold no energy, so it has a served-ratio bar only."""
    ceiling = day_rows().filter((pl.col("method") == "greedy") & (pl.col("dataset") == "milan")).with_columns(
        pl.lit("ceiling").alias("method"), (pl.col("sr_mean") + 0.2).alias("sr_mean"),
        pl.lit(None, pl.Float64).alias("energy_kj_per_slot"), pl.lit(None, pl.Float64).alias("energy_efficiency"))
    kw = {**KW, "labels": {**LABELS, "ceiling": "Ceiling"}, "classes": {**CLASSES, "ceiling": "upper bound"},
          "run_order": ["static", "greedy", "dswm", "ceiling"],
          "class_order": ["world model", "model-free", "deployment", "upper bound"]}
    data = results.draw_main(pl.concat([day_rows(), ceiling]), dataset="milan", source="demo",
                             out=common.outputs(tmp_path / "main"), **kw)
    row = data.filter((pl.col("method") == "ceiling") & (pl.col("split") == "id")).row(0, named=True)
    assert row["sr_mean"] == pytest.approx(0.91) and row["energy_kj_per_slot"] is None
    assert row["energy_efficiency"] is None
    assert (tmp_path / "main.png").stat().st_size > 0


def test_ood_figure_degradation_is_weekday_minus_holiday_per_seed(tmp_path):
    data = results.draw_ood(day_rows(), dataset="milan", source="demo", out=common.outputs(tmp_path / "ood"), **KW)
    deg = dict(data.select("method", "degradation").unique().iter_rows())
    # dswm: seed 0 0.81 - 0.90 = -0.09, seed 1 0.79 - 0.86 = -0.07 -> -0.08; static: 0.60-0.50, 0.62-0.52 -> 0.10
    assert deg["dswm"] == pytest.approx(-0.08) and deg["static"] == pytest.approx(0.10)
    assert deg["greedy"] == pytest.approx(-0.04)  # 0.71 - 0.75 on both seeds
    day13 = data.filter((pl.col("method") == "dswm") & (pl.col("day") == 13)).row(0, named=True)
    assert day13["sr_mean"] == pytest.approx(0.88) and day13["split"] == "ood"


def test_cross_dataset_figure_keeps_methods_of_more_than_one_dataset(tmp_path):
    data = results.draw_cross(day_rows(), source={"Milan": "demo", "Shanghai": "demo"},
                              out=common.outputs(tmp_path / "cross"), **KW)
    assert sorted(data["method"].unique()) == ["dswm", "greedy"]  # static runs on Milan only
    sh = data.filter((pl.col("dataset") == "shanghai") & (pl.col("method") == "greedy") & (pl.col("split") == "ood"))
    assert sh["sr_mean"].to_list() == [pytest.approx(0.45)] and sh["seeds"].to_list() == [1]


def test_eda_figure_draws_each_dataset_cycle_and_daily_totals(tmp_path):
    stats = {"milan": {"source": "demo", "zero_cell_rate": 0.0, "top5_share": 0.13,
                       "daily_cycle": {"weekday": [1.0] * 144, "weekend": [2.0] * 144},
                       "daily_totals": [{"index": 0, "label": "2013-11-01", "split": "train", "eval": None,
                                         "total": 10.0},
                                        {"index": 1, "label": "2013-12-24", "split": "test", "eval": "ood",
                                         "total": 7.0}]}}
    data = eda.draw_eda(stats, profile="smoke", out=common.outputs(tmp_path / "eda"))
    daily = data.filter(pl.col("panel") == "daily")
    assert daily["series"].to_list() == ["train", "ood"] and daily["value"].to_list() == [10.0, 7.0]
    assert data.filter((pl.col("panel") == "cycle") & (pl.col("series") == "weekend"))["value"].sum() == 288.0


def test_eda_statistics_without_their_keys_are_refused_with_the_file(tmp_path):
    bad = tmp_path / "eda.json"
    bad.write_text('{"dataset": "milan"}')
    with pytest.raises(ValueError, match=r"eda.json: EDA statistics lack key 'daily_cycle'"):
        eda.read_stats({"milan": bad})
