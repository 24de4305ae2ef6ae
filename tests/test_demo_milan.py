"""Milan demo: the hotspot migration of the real frames, the fitted residual field, and what the field keeps.

Real reference: the shared full-grid frames `milan_internet_grid_10min.npz`, frames 0-50 (2013-11-03 00:00-08:20
CET), crop grid rows/cols 40..59 counted from the south; measured 0.4909 (top-20 share-map overlap 18 slots
apart) and 5.54% (energy outside the first singular component). The demo must land within 0.1 of the first and
30% (relative) of the second on its prepared data over the same slots.
"""
from __future__ import annotations

import copy
import dataclasses
import datetime as dt
from pathlib import Path

import numpy as np
import pytest
import yaml

from conftest import dataset_of, prepare_from_config
from prep import stats
from prep.demo import milan as demo
from prep.eda import hotspot_migration
from prep.pipeline import generate_demo
from prep.tensor import load

ROOT = Path(__file__).resolve().parents[1]
REAL = ROOT.parent / "shared" / "data" / "real" / "milan"
REAL_OVERLAP = 0.4909  # 27/55, measured below on the real frames
REAL_ENERGY = 0.05537
K, LAG, SLOTS = 20, 18, 51


def _config() -> dict:
    return yaml.safe_load((ROOT / "config.yaml").read_text())


def _real_window() -> np.ndarray:
    """Real frames 0..50 of the shared npz on the configured crop, as (51, 20, 20) rows from the south."""
    crop = dataset_of(_config(), "milan").crop
    with np.load(REAL / "milan_internet_grid_10min.npz") as f:
        north_up, t, ids = f["internet"], f["time_interval_ms"], f["square_id"]
    assert ids[0, 0] == 9901 and ids[99, 0] == 1  # row 0 is the northernmost grid row
    south_up = north_up[:, ::-1, :]
    assert t[0] == 1383433200000 and np.all(np.diff(t[:SLOTS]) == 600_000)  # 2013-11-03 00:00 CET, 10-min steps
    window = south_up[:SLOTS, crop.first_row: crop.first_row + crop.rows, crop.first_col: crop.first_col + crop.cols]
    # The same squares as the shipped (south-up) asset frames, whose ids are (30 + r) * 100 + (30 + c) + 1.
    assets = demo.load_assets()
    r0, c0 = crop.first_row - assets["frames_first_row"], crop.first_col - assets["frames_first_col"]
    assert np.array_equal(assets["frames"][:SLOTS, r0: r0 + crop.rows, c0: c0 + crop.cols], window)
    assert np.array_equal(ids[::-1][crop.first_row, crop.first_col: crop.first_col + 2],
                          [crop.first_row * 100 + crop.first_col + 1, crop.first_row * 100 + crop.first_col + 2])
    return window.astype(np.float64)


def _plain_figures(frames: np.ndarray) -> tuple[float, float]:
    """The two figures written out directly (an independent check of prep.stats)."""
    x = frames.reshape(len(frames), -1)
    share = x / x.sum(axis=1, keepdims=True)
    top = [set(np.argsort(-s)[:K].tolist()) for s in share]
    overlap = np.mean([len(top[t] & top[t + LAG]) / K for t in range(len(x) - LAG)])
    s = np.linalg.svd(x, compute_uv=False)
    return float(overlap), float(1 - s[0] ** 2 / np.sum(s ** 2))


def test_real_frames_migrate_far_more_than_two_profiles_allow():
    window = _real_window()
    fig = stats.hotspot_migration(window, K, LAG)
    assert fig["top_k_share_overlap"] == pytest.approx(27 / 55, abs=1e-12)
    assert fig["energy_outside_first_component"] == pytest.approx(REAL_ENERGY, abs=2e-5)
    assert _plain_figures(window) == pytest.approx((fig["top_k_share_overlap"],
                                                    fig["energy_outside_first_component"]), abs=1e-12)


def test_migration_figures_on_hand_made_frames():
    rng = np.random.default_rng(0)
    base = rng.gamma(2.0, 1.0, (10, 10))
    scaled = base[None] * rng.uniform(0.5, 2.0, 30)[:, None, None]  # one map, scaled: nothing moves
    assert stats.top_share_overlap(scaled, 5, 3) == 1.0
    assert stats.energy_outside_first_component(scaled) == pytest.approx(0.0, abs=1e-12)
    a, b = np.zeros((2, 4)), np.zeros((2, 4))
    a[0, :2], b[1, 2:] = 1.0, 1.0  # two disjoint hotspot pairs, alternating
    alt = np.stack([a, b] * 5)
    assert stats.top_share_overlap(alt, 2, 1) == 0.0 and stats.top_share_overlap(alt, 2, 2) == 1.0
    assert stats.energy_outside_first_component(alt) == pytest.approx(0.5)
    assert stats.top_share_overlap(np.zeros((5, 3)), 1, 1) is None
    assert stats.energy_outside_first_component(np.zeros((5, 3))) is None


def test_demo_reproduces_the_real_hotspot_migration(tmp_path):
    config = copy.deepcopy(_config())
    m = config["datasets"]["milan"]
    m["split"] = {"train": ["2013-11-03", "2013-11-03"], "test": ["2013-11-04", "2013-11-05"]}
    m["eval_days"] = {"id": {"rule": "test_positions", "values": [0], "count": 1},
                      "ood": {"rule": "test_positions", "values": [1], "count": 1}}
    generate_demo(dataset_of(config, "milan"), "milan", tmp_path / "raw")
    prepare_from_config(config, "milan", raw=[str(tmp_path / "raw")], out_dir=tmp_path / "data", reference_meta=None)
    t = load(tmp_path / "data")
    fig = hotspot_migration(t, config["datasets"]["common"]["top_share_frac"])
    assert fig["window"] == {"day": "2013-11-03", "day_index": 0, "first_slot": 0, "slots": SLOTS,
                             "basis": "real frames' window"}
    assert fig["top_k"] == K and fig["lag_slots"] == LAG
    overlap, energy = fig["top_k_share_overlap"], fig["energy_outside_first_component"]
    assert (overlap, energy) == pytest.approx(_plain_figures(t.demand[0, :SLOTS].astype(np.float64)), abs=1e-9)
    # Measured with seed 0: 0.588 and 4.53% (seeds 0..19: 0.50 +- 0.05 and 4.7% +- 0.3%); without the residual
    # field (field_sigma 0) 0.68 and 2.5%, and the two-profile demo before it 0.83 and 1.1%: both fail here.
    assert abs(overlap - REAL_OVERLAP) <= 0.1
    assert abs(energy / REAL_ENERGY - 1) <= 0.3


def _milan():
    return dataset_of(_config(), "milan")


def test_residual_field_parameters_are_the_fitted_ones():
    cfg = _milan()
    assets = demo.load_assets()
    tau = demo.fit_persistence(assets["series_time"], assets["series_a"], assets["series_b"])
    assert cfg.demo.field_tau_slots == pytest.approx(tau, abs=0.05)
    flat = demo.expected_values(dataclasses.replace(cfg, demo=dataclasses.replace(cfg.demo, field_sigma=0.0)))
    idx = np.searchsorted(flat["time_ms"], assets["frames_time"])
    crop = cfg.crop
    r0, c0 = crop.first_row - assets["frames_first_row"], crop.first_col - assets["frames_first_col"]
    frames = assets["frames"][:, r0: r0 + crop.rows, c0: c0 + crop.cols]
    level = (flat["totals"] / len(flat["time_ms"])).reshape(crop.rows, crop.cols)
    fit = demo.fit_residual_field(frames, assets["frames_time"], flat["mean"][idx].reshape(frames.shape), level,
                                  cfg.demo.field_tau_slots)
    assert cfg.demo.field_sigma == pytest.approx(fit["sigma"], abs=5e-4)
    assert cfg.demo.field_smooth_cells == pytest.approx(fit["smooth_cells"], abs=5e-4)
    # The same fit's slot-to-slot part is of the order of the demo's noise_sigma.
    assert 0.05 <= fit["noise_sigma"] <= cfg.demo.noise_sigma


def test_residual_field_has_the_configured_statistics():
    tau, ell = 19.4, 0.667
    x = demo.residual_field(np.random.default_rng(5), 6000, 20, 20, tau, ell)
    assert x.shape == (6000, 20, 20)
    assert x.mean() == pytest.approx(0.0, abs=0.05) and x.var() == pytest.approx(1.0, abs=0.08)
    lag1 = np.mean(x[1:] * x[:-1]) / x.var()
    assert lag1 == pytest.approx(np.exp(-1 / tau), abs=0.01)
    rho = demo.spatial_correlation(ell, (1, 2))
    got = [np.mean(x[:, :, d:] * x[:, :, :-d]) / x.var() for d in (1, 2)]
    assert got == pytest.approx(rho.tolist(), abs=0.02)
    white = demo.residual_field(np.random.default_rng(5), 500, 4, 4, 0.0, 0.0)
    assert abs(np.mean(white[1:] * white[:-1])) < 0.05  # tau = 0: independent slots


def test_field_keeps_totals_weekly_cycle_and_holiday_week():
    cfg = _milan()
    with_field = demo.expected_values(cfg)
    without = demo.expected_values(dataclasses.replace(cfg, demo=dataclasses.replace(cfg.demo, field_sigma=0.0)))
    # Each square's two-month total is the real one, with and without the field.
    for model in (with_field, without):
        assert np.allclose(model["mean"].sum(axis=0), model["totals"], rtol=1e-9)
    # The damped profiles keep every square's daily totals of the two real profiles: the weekly cycle and the
    # Christmas week are the real ones.
    assets = demo.load_assets()
    a = assets["series_a"] / assets["series_a"].mean()
    b = assets["series_b"] / assets["series_b"].mean()
    level = without["totals"] / len(a)
    plain = level * (b[:, None] + without["mix"] * (a - b)[:, None])
    daily = lambda v: v.reshape(-1, 144, v.shape[1]).sum(axis=1)  # noqa: E731
    assert np.allclose(daily(without["mean"]), daily(plain), rtol=1e-9)
    assert without["damp"].max() > 0.5  # the within-day swing IS damped for some squares
    # The field moves demand between squares and hours, hardly between days: crop totals per day within 5%
    # (measured: -3.6% .. +3.0%).
    crop_days = daily(with_field["mean"]).sum(axis=1) / daily(without["mean"]).sum(axis=1)
    assert np.all(np.abs(crop_days - 1) < 0.05)
    first = dt.date(2013, 11, 1)
    day = lambda d: (d - first).days  # noqa: E731
    crop = daily(with_field["mean"]).sum(axis=1)
    assert crop[day(dt.date(2013, 12, 25))] < 0.5 * crop[day(dt.date(2013, 11, 4))]  # the real Christmas dip
    # Seeded: the same seed gives the same field, another seed another one.
    other = demo.expected_values(dataclasses.replace(cfg, demo=dataclasses.replace(cfg.demo, seed=1)))
    assert np.array_equal(demo.expected_values(cfg)["mean"], with_field["mean"])
    assert not np.allclose(other["mean"], with_field["mean"])
