"""The qualitative figures (paper Figs. 14-16 and Section V-K):

* ``qualitative_milan`` (paper Fig. 14): the full city on the real Milano GRID with the crop outlined, the true
  demand map of the crop at a busy slot of a test day, the DSWM world model's one-step prediction of it and the
  per-cell error. The city panel shows the real two-month internet totals per square shipped with the project
  (``prep/assets/milan/square_totals_2mo.csv``, the Telecom Italia data whatever the run's data source); the crop
  panels are the prepared tensor (demo or raw) and the world-model quality job's one-step maps
  (``dswm.methods.dswm.quality``).
* ``qualitative_shanghai`` / ``qualitative_yjmob`` (paper Figs. 15, 16): the full region (training-period session
  starts / records per cell on the dataset's full grid, read from the raw files with the project's readers) with
  the crop outlined, the true map of the crop at a busy slot of the first ID test day, and the mean map of the
  weekday and of the weekend days (YJMob: the pseudo-weekend of the recovered week) of the prepared tensor.
* ``qualitative_trajectories`` (Section V-K; the paper draws no such figure): one day of the fleet's positions per
  slot for DSWM and Greedy over that day's mean demand map, from the main evaluations' trajectory.npz.

The busy slot of a day is the slot 1..T-1 with the largest total demand of the crop (slot 0 has no prediction).
Maps are in the tensor's normalized demand units; tensor row 0 is the southern row (drawn at the bottom). The data
they draw is read by ``dswm.figures.regions``.
"""
from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence

import numpy as np
import polars as pl
from matplotlib.collections import PolyCollection
from matplotlib.colors import LogNorm, TwoSlopeNorm
from matplotlib.patches import Polygon, Rectangle

from dswm.figures.common import plt, save_figure
from dswm.figures.regions import (busy_slot, check_region, crop_origin, day_profiles, milan_crop_outline,
                                  read_milan_grid, read_milan_totals, shanghai_region, yjmob_region)
from dswm.protocol.tables import DATASET_LABELS

CAPTIONS = {
    "milan": ("Paper Fig. 14 (qualitative_milan): world-model prediction on Milan: full-city context on the Milano "
              "GRID (real two-month totals, crop outlined), true demand of the crop at a busy test slot, the DSWM "
              "world model's one-step prediction of it and the per-cell error (prediction - truth)."),
    "shanghai": ("Paper Fig. 15 (qualitative_shanghai): Shanghai: full-region training-period session starts (crop "
                 "outlined), true demand of the crop at a busy test slot, weekday and weekend mean maps."),
    "yjmob": ("Paper Fig. 16 (qualitative_yjmob): YJMob100K: full-region training-period records (crop outlined), "
              "true demand of the crop at a busy test slot, weekday and pseudo-weekend mean maps."),
    "trajectories": ("Paper Section V-K (qualitative_trajectories; no paper figure): one test day of the fleet's "
                     "positions per slot for each method over the day's mean demand map (circle: start, triangle: "
                     "end, grey x: returning or charging, black squares: charging stations)."),
}


# ---- drawing ------------------------------------------------------------------------------------------------
def _map_frame(panel: str, values: np.ndarray) -> pl.DataFrame:
    """A (R, C) map as CSV rows: panel, row (0 = south), col, value."""
    r, c = np.meshgrid(np.arange(values.shape[0]), np.arange(values.shape[1]), indexing="ij")
    return pl.DataFrame({"panel": panel, "row": r.ravel(), "col": c.ravel(), "value": values.ravel().astype(float)})


def _crop_map(ax, values: np.ndarray, cell_m: float, title: str, unit: str = "demand (normalized units)", **kw):
    """Draw a crop map (row 0 south) in km with a colour bar labelled ``unit``."""
    rows, cols = values.shape
    im = ax.imshow(values, origin="lower", extent=(0, cols * cell_m / 1e3, 0, rows * cell_m / 1e3), **kw)
    ax.set_title(title, fontsize=9)
    ax.set_xlabel("km east")
    ax.set_ylabel("km north")
    plt.colorbar(im, ax=ax, fraction=0.046, pad=0.03).set_label(unit, fontsize=8)
    return im


def draw_milan(*, ids: np.ndarray, rings: np.ndarray, totals: pl.DataFrame, outline: np.ndarray, true: np.ndarray,
               pred: np.ndarray, cell_m: float, when: str, profile: str, source: str,
               out: Mapping[str, str | Path]) -> pl.DataFrame:
    """Draw paper Fig. 14 and write it (PNG, PDF and the CSV of the numbers drawn).

    Args:
        ids, rings: the Milano GRID (:func:`read_milan_grid`); totals: the city's totals (:func:`read_milan_totals`);
        outline: (4, 2) the crop's corners (:func:`milan_crop_outline`); true, pred: (R, C) the crop's true and
        predicted maps at the slot ``when`` describes.
    Returns:
        The CSV's table: panel "city" rows (square_id, value = total), then panels "true", "predicted" and "error"
        (row, col, value; error = predicted - true).
    """
    value = dict(zip(totals["square_id"].to_list(), totals["internet"].to_list()))
    city = np.array([value.get(int(i), np.nan) for i in ids])
    fig, axes = plt.subplots(1, 4, figsize=(17.0, 4.4))
    ax = axes[0]
    positive = city[np.isfinite(city) & (city > 0)]
    coll = PolyCollection(rings, array=np.where(city > 0, city, np.nan), cmap="magma",
                          norm=LogNorm(vmin=positive.min(), vmax=positive.max()), edgecolors="none",
                          antialiaseds=False)
    ax.add_collection(coll)
    ax.add_patch(Polygon(outline, closed=True, fill=False, edgecolor="cyan", lw=1.5))
    ax.set_xlim(rings[..., 0].min(), rings[..., 0].max())
    ax.set_ylim(rings[..., 1].min(), rings[..., 1].max())
    ax.set_aspect(1.0 / np.cos(np.radians(rings[..., 1].mean())))
    ax.set_xlabel("longitude")
    ax.set_ylabel("latitude")
    ax.set_title("(a) Milan, Milano GRID: real internet totals\n2013-11-01..2014-01-01 (crop outlined)", fontsize=9)
    plt.colorbar(coll, ax=ax, fraction=0.046, pad=0.03).set_label("internet activity per square", fontsize=8)
    vmax = float(max(np.nanmax(true), np.nanmax(pred)))
    _crop_map(axes[1], true, cell_m, f"(b) true demand\n{when}", cmap="viridis", vmin=0.0, vmax=vmax)
    _crop_map(axes[2], pred, cell_m, "(c) DSWM one-step prediction", cmap="viridis", vmin=0.0, vmax=vmax)
    err = pred - true
    span = float(np.nanmax(np.abs(err))) or 1.0
    _crop_map(axes[3], err, cell_m, "(d) error (prediction - truth)", "error (normalized units)", cmap="RdBu_r",
              norm=TwoSlopeNorm(vcenter=0.0, vmin=-span, vmax=span))
    fig.tight_layout(rect=(0, 0.06, 1, 0.97))
    data = pl.concat([pl.DataFrame({"panel": "city", "square_id": ids, "value": city}),
                      _map_frame("true", true), _map_frame("predicted", pred), _map_frame("error", err)],
                     how="diagonal_relaxed")
    save_figure(fig, data, **out, profile=profile, source=source, caption=CAPTIONS["milan"])
    return data


def draw_region(*, dataset: str, label: str, region: np.ndarray, origin: tuple[int, int], true: np.ndarray,
                weekday: np.ndarray, weekend: np.ndarray, cell_m: float, region_what: str, when: str,
                counts: tuple[int, int], weekend_word: str, profile: str, source: str,
                out: Mapping[str, str | Path]) -> pl.DataFrame:
    """Draw paper Fig. 15 or 16 and write it (PNG, PDF and the CSV of the numbers drawn).

    Args:
        dataset: "shanghai" or "yjmob" (the caption); label: its display name.
        region: (H, W) the full grid's training-period counts (row 0 south); origin: the crop's (first row, first
            column) on it; true, weekday, weekend: (R, C) crop maps; counts: (weekday days, weekend days) averaged;
            region_what: what ``region`` counts; when: the true map's day and slot; weekend_word: "weekend" or
            "pseudo-weekend".
    Returns:
        The CSV's table: panels "region" (row, col of the full grid, value = count), "true", "weekday", "weekend".
    """
    fig, axes = plt.subplots(1, 4, figsize=(17.0, 4.4))
    ax = axes[0]
    h, w = region.shape
    km = cell_m / 1e3
    shown = np.where(region > 0, region, np.nan)
    im = ax.imshow(shown, origin="lower", extent=(0, w * km, 0, h * km), cmap="magma",
                   norm=LogNorm(vmin=max(1.0, float(np.nanmin(shown))), vmax=float(np.nanmax(shown))))
    ax.set_facecolor("0.85")
    rows, cols = true.shape
    ax.add_patch(Rectangle((origin[1] * km, origin[0] * km), cols * km, rows * km, fill=False, edgecolor="cyan",
                           lw=1.5))
    ax.set_title(f"(a) {label}: full region, {region_what}\n(crop outlined; grey: none)", fontsize=9)
    ax.set_xlabel("km east")
    ax.set_ylabel("km north")
    plt.colorbar(im, ax=ax, fraction=0.046, pad=0.03).set_label(region_what, fontsize=8)
    _crop_map(axes[1], true, cell_m, f"(b) true demand\n{when}", cmap="viridis", vmin=0.0)
    vmax = float(max(weekday.max(), weekend.max()))
    _crop_map(axes[2], weekday, cell_m, f"(c) weekday mean map ({counts[0]} days)", cmap="viridis", vmin=0.0,
              vmax=vmax)
    _crop_map(axes[3], weekend, cell_m, f"(d) {weekend_word} mean map ({counts[1]} days)", cmap="viridis",
              vmin=0.0, vmax=vmax)
    fig.tight_layout(rect=(0, 0.06, 1, 0.97))
    data = pl.concat([_map_frame("region", region), _map_frame("true", true), _map_frame("weekday", weekday),
                      _map_frame("weekend", weekend)])
    save_figure(fig, data, **out, profile=profile, source=source, caption=CAPTIONS[dataset])
    return data


def draw_trajectories(trajectories: Mapping[str, tuple[np.ndarray, np.ndarray]], *, background: np.ndarray,
                      cell_m: float, labels: Mapping[str, str], when: str, profile: str, source: str,
                      out: Mapping[str, str | Path]) -> pl.DataFrame:
    """Draw one day of the fleet's trajectories per method and write it (PNG, PDF and the CSV of the positions).

    Args:
        trajectories: {method: (positions (T, K, 2) metres, status (T, K); 0 active, 1 returning, 2 charging)}.
        background: (R, C) the day's mean demand map.
    Returns:
        The CSV's table: method, uav, slot, x_m, y_m, status.
    """
    rows, cols = background.shape
    width, height = cols * cell_m, rows * cell_m
    stations = np.array([[width / 4, height / 4], [3 * width / 4, height / 4], [width / 4, 3 * height / 4],
                         [3 * width / 4, 3 * height / 4]]) / 1e3
    fig, axes = plt.subplots(1, len(trajectories), figsize=(5.6 * len(trajectories), 5.0), squeeze=False)
    frames = []
    cmap = plt.get_cmap("tab20")
    for ax, (method, (pos, status)) in zip(axes[0], trajectories.items()):
        _crop_map(ax, background, cell_m, f"{labels.get(method, method)}: {when}", "mean demand of the day",
                  cmap="Greys", vmin=0.0)
        km = pos / 1e3
        for k in range(pos.shape[1]):
            color = cmap(k % 20)
            ax.plot(km[:, k, 0], km[:, k, 1], "-", color=color, lw=0.9, alpha=0.9)
            ax.plot(km[0, k, 0], km[0, k, 1], "o", color=color, ms=4)
            ax.plot(km[-1, k, 0], km[-1, k, 1], "^", color=color, ms=5, mec="k", mew=0.4)
            away = status[:, k] != 0
            ax.plot(km[away, k, 0], km[away, k, 1], "x", color="0.45", ms=3, lw=0)
        ax.plot(stations[:, 0], stations[:, 1], "s", color="k", ms=6)
        ax.set_xlim(0, width / 1e3)
        ax.set_ylim(0, height / 1e3)
        t, k = np.meshgrid(np.arange(pos.shape[0]), np.arange(pos.shape[1]), indexing="ij")
        frames.append(pl.DataFrame({"method": method, "uav": k.ravel(), "slot": t.ravel(),
                                    "x_m": pos[..., 0].ravel().astype(float), "y_m": pos[..., 1].ravel().astype(float),
                                    "status": status.ravel().astype(np.int64)}))
    fig.tight_layout(rect=(0, 0.08, 1, 0.97))
    data = pl.concat(frames)
    save_figure(fig, data, **out, profile=profile, source=source, caption=CAPTIONS["trajectories"])
    return data


# ---- from the result files to a figure (the scripts' entry points) ---------------------------------------------
def _slot_time(slot: int, slots_per_day: int) -> str:
    minutes = round(slot * 24 * 60 / slots_per_day)
    return f"{minutes // 60:02d}:{minutes % 60:02d}"


def milan_figure(*, maps: str | Path, meta: str | Path, grid: str | Path, totals: str | Path, profile: str,
                 out: Mapping[str, str | Path]) -> pl.DataFrame:
    """Paper Fig. 14 from the quality job's maps.npz (one replayed day: ``true`` and ``one_step`` (T, R, C)), the
    prepared meta.json and the two Milan assets; the slot drawn is the day's :func:`busy_slot`."""
    from prep.tensor import read_meta

    m = read_meta(meta, keys=("dataset", "source", "grid", "slots_per_day"))
    with np.load(maps) as z:
        true, pred = z["true"], z["one_step"]
        label, split, seed = str(z["label"]), str(z["split"]), int(z["seed"])
    slot = busy_slot(true)
    ids, rings = read_milan_grid(grid)
    when = f"{label} ({split}) {_slot_time(slot, m['slots_per_day'])}, slot {slot}; DSWM seed {seed}"
    return draw_milan(ids=ids, rings=rings, totals=read_milan_totals(totals), outline=milan_crop_outline(ids, rings,
                      m["grid"]), true=true[slot], pred=pred[slot], cell_m=float(m["grid"]["cell_m"]), when=when,
                      profile=profile, source=m["source"], out=out)


def region_figure(*, dataset: str, settings: Mapping, raw: Sequence[str | Path], tensor_dir: str | Path,
                  profile: str, out: Mapping[str, str | Path]) -> pl.DataFrame:
    """Paper Fig. 15 (Shanghai) or 16 (YJMob) from the raw files (the full region), the prepared tensor and its
    meta.json; the true map is the first ID test day's :func:`busy_slot`.

    Args:
        settings: the plain ``dswm.settings.prep_slice`` of ``dataset`` (its ``datasets.<dataset>`` section).
        raw: the raw files or the demo directory (``prep.pipeline.raw_inputs``).
    """
    from prep.config import dataset_from_plain
    from prep.tensor import load

    cfg = dataset_from_plain(dataset, settings["settings"])
    files = []
    for p in map(Path, raw):  # as the prepare rule reads them: a directory's visible files, or the file
        files.extend(sorted(q for q in p.iterdir() if q.is_file() and not q.name.startswith(".")) if p.is_dir()
                     else [p])
    region = shanghai_region(cfg, files) if dataset == "shanghai" else yjmob_region(cfg, files)
    tensor = load(tensor_dir)
    meta = tensor.meta
    check_region(region, meta)
    day = int(meta["eval_days"]["id"][0])
    slot = busy_slot(tensor.demand[day])
    weekday, weekend, n_wd, n_we = day_profiles(tensor.demand, meta)
    what = "training-period session starts" if dataset == "shanghai" else "training-period records"
    when = f"{tensor.labels[day]} (id) {_slot_time(slot, meta['slots_per_day'])}, slot {slot}"
    return draw_region(dataset=dataset, label=DATASET_LABELS.get(dataset, dataset), region=region,
                       origin=crop_origin(meta), true=tensor.demand[day, slot], weekday=weekday, weekend=weekend,
                       cell_m=float(meta["grid"]["cell_m"]), region_what=what, when=when, counts=(n_wd, n_we),
                       weekend_word="weekend" if dataset == "shanghai" else "pseudo-weekend", profile=profile,
                       source=meta["source"], out=out)


def trajectories_figure(*, trajectories: Sequence[str | Path], methods: Sequence[str], labels: Mapping[str, str],
                        tensor_dir: str | Path, profile: str, out: Mapping[str, str | Path]) -> pl.DataFrame:
    """One day of trajectories from the main evaluations' trajectory.npz (``id_pos``, ``id_status``, ``id_day``:
    the first ID day) of ``methods``, over that day's mean map of the prepared tensor.

    Raises:
        ValueError: the files hold different days.
    """
    from prep.tensor import load

    tensor = load(tensor_dir)
    runs, days = {}, set()
    for method, path in zip(methods, trajectories, strict=True):
        with np.load(path) as z:
            runs[method] = (z["id_pos"], z["id_status"])
            days.add(int(z["id_day"]))
    if len(days) != 1:
        raise ValueError(f"trajectory files {list(map(str, trajectories))} hold the ID days {sorted(days)}; expected "
                         f"one day for every method")
    day = days.pop()
    when = f"{tensor.labels[day]} (id), {tensor.demand.shape[1]} slots"
    return draw_trajectories(runs, background=tensor.demand[day].mean(0), cell_m=float(tensor.meta["grid"]["cell_m"]),
                             labels=labels, when=when, profile=profile, source=tensor.meta["source"], out=out)
