"""A small clean pipeline tree for testing and demonstrating the audit.

`build_clean_tree(root)` writes, under `root`, what the pipeline would have produced on two tiny datasets:
raw files in the published Milan and YJMob formats (results/raw/...), the prepared tensors made by the real
`prep` functions (results/data/...), per-day result files of static, greedy and one learning method with a
training manifest and checkpoint, trajectories and the calibration record. Test days carry more demand than
training days, so every training statistic differs from its all-days and test-segment values.
"""
from __future__ import annotations

import copy
import csv
import datetime as dt
import gzip
import json
import os
from pathlib import Path
from zoneinfo import ZoneInfo

import numpy as np
import polars as pl
import yaml

REPO = Path(__file__).resolve().parents[1]
METHODS = ["static", "greedy", "dswm"]
T0 = 1_700_000_000.0
"""File times of the fixture (seconds since the epoch): checkpoint, then manifest, then results."""


def fixture_config() -> dict:
    """The repository's config.yaml shrunk to a 5x5 Milan crop and a 5x5 YJMob crop on a 12x12 grid."""
    cfg = copy.deepcopy(yaml.safe_load((REPO / "config.yaml").read_text()))
    cfg["profile"] = "smoke"
    cfg["profiles"]["smoke"] = {"datasets": ["milan", "yjmob"], "seeds": {"milan": [0], "yjmob": [0]},
                                "eval_days": {"id": None, "ood": None}}
    cfg["methods"]["run"] = list(METHODS)
    m = cfg["datasets"]["milan"]
    m["crop"] = {"first_row": 40, "first_col": 40, "rows": 5, "cols": 5}
    m["split"] = {"train": ["2013-11-01", "2013-11-04"], "test": ["2013-12-21", "2013-12-26"]}
    m["eval_days"] = {"id": {"rule": "test_positions", "values": [0, 1, 2], "count": 3},
                      "ood": {"rule": "test_positions", "values": [3, 4], "count": 2}}
    y = cfg["datasets"]["yjmob"]
    y.update(full_size=12, n_days=16, crop={"rows": 5, "cols": 5}, split={"train": [0, 9], "test": [10, 15]},
             week={"min_lag": 2, "max_lag": 5, "n_weekend_phases": 1})
    y["eval_days"] = {"id": {"rule": "first_weekdays", "values": [], "count": 2},
                      "ood": {"rule": "first_weekend", "values": [], "count": 1}}
    return cfg


def _milan_raw(cfg: dict, out: Path, rng: np.random.Generator) -> list[Path]:
    """Daily Milan files (tab-separated, no header, blank = no activity) for the crop's squares; test days are
    busier, the more so the further east (so the all-days mean map differs in shape from the training one)."""
    m = cfg["datasets"]["milan"]
    crop, tz = m["crop"], ZoneInfo(m["timezone"])
    ids = [(crop["first_row"] + r) * m["full_cols"] + crop["first_col"] + c + 1
           for r in range(crop["rows"]) for c in range(crop["cols"])]
    base = rng.gamma(2.0, 50.0, len(ids))
    east = np.array([c for r in range(crop["rows"]) for c in range(crop["cols"])]) / max(crop["cols"] - 1, 1)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for seg, factor in (("train", 1.0), ("test", 1.7)):
        a, b = (dt.date.fromisoformat(s) for s in m["split"][seg])
        for k in range((b - a).days + 1):
            day = a + dt.timedelta(days=k)
            t0 = int(dt.datetime.combine(day, dt.time(0), tzinfo=tz).timestamp() * 1000)
            lines = []
            for s in range(144):
                shape = 0.3 + np.sin(np.pi * s / 144) ** 2
                for i, sq in enumerate(ids):
                    v = base[i] * shape * factor ** (1.0 + east[i]) * rng.lognormal(0.0, 0.3)
                    lines.append(f"{sq}\t{t0 + s * 600_000}\t39\t1.0\t\t\t0.5\t{v:.6f}")
                    lines.append(f"{sq}\t{t0 + s * 600_000}\t33\t\t0.2\t\t\t" +
                                 (f"{0.05 * v:.6f}" if rng.random() < 0.7 else ""))
            p = out / f"sms-call-internet-mi-{day.isoformat()}.txt"
            p.write_text("\n".join(lines) + "\n")
            paths.append(p)
    return paths


def _yjmob_raw(cfg: dict, out: Path, rng: np.random.Generator) -> Path:
    """yjmob100k-dataset1.csv.gz: period-5 activity (phase 4 low), busier test days, some masked rows."""
    y = cfg["datasets"]["yjmob"]
    out.mkdir(parents=True, exist_ok=True)
    path = out / "yjmob100k-dataset1.csv.gz"
    with gzip.open(path, "wt", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["uid", "d", "t", "x", "y"])
        for uid in range(300):
            home = np.clip(np.round(rng.normal(6, 1.5, 2)), 1, y["full_size"]).astype(int)
            for d in range(y["n_days"]):
                lam = 8.0 * (0.3 if d % 5 == 4 else 1.0) * (1.6 if d >= y["split"]["test"][0] else 1.0)
                for _ in range(rng.poisson(lam)):
                    x, yy = np.clip(home + np.round(rng.normal(0, 1.5, 2)), 1, y["full_size"]).astype(int)
                    w.writerow([uid, d, int(rng.integers(0, 48)), int(x), int(yy)])
            if uid % 10 == 0:
                w.writerow([uid, y["n_days"] - 1, 5, 999, 999])
    return path


def prepare(cfg: dict, root: Path, *, only: str | None = None) -> None:
    """Writes results/data/<dataset>/demand.parquet + meta.json with the real prep functions.

    Args:
        cfg: the fixture config; root: the tree; only: prepare this dataset alone (the reference dataset's
            training mean is then read back from its meta.json).
    """
    from prep import milan, tensor, yjmob
    from prep.config import common_config, dataset_config
    from prep.days import pick_eval_days

    common = common_config(cfg)
    ref_meta = root / "results" / "data" / common.kappa_reference / "meta.json"
    ref = json.loads(ref_meta.read_text())["train_mean_normalized"] if only and ref_meta.is_file() else None
    for name, module in (("milan", milan), ("yjmob", yjmob)):
        if only is not None and name != only:
            continue
        dcfg = dataset_config(cfg, name)
        paths = sorted((root / "results" / "raw" / name / "demo").iterdir())
        raw = module.build(dcfg, paths)
        ev = pick_eval_days(raw.days, raw.weekend, dcfg.eval_days, dataset=name)
        demand, meta = tensor.finalize(raw, common=common, cfg=dcfg, source="demo", eval_days=ev,
                                       reference_mean=None if name == common.kappa_reference else ref)
        tensor.write(root / "results" / "data" / name, demand, meta)
        if name == common.kappa_reference:
            ref = meta["train_mean_normalized"]


def write_results(cfg: dict, root: Path, ds: str, method: str, seed: int, *, obs_hash: str | None = None,
                  days_override: dict[str, list[int]] | None = None) -> Path:
    """Writes days.parquet (+ trajectory.npz) of one job with the hashes a clean evaluation records."""
    from dswm.config import Scenario, stable_hash
    from dswm.env import Grid, initial_positions, obs_spec_hash
    from prep.tensor import load

    scenario = Scenario.from_dict(cfg["scenario"])
    t = load(root / "results" / "data" / ds)
    grid = Grid(rows=t.grid.rows, cols=t.grid.cols, cell_m=t.grid.cell_m)
    labels = t.labels
    ev = {k: list(map(int, t.eval_days(k))) for k in ("id", "ood")}
    eval_hash = stable_hash({"dataset": ds, **{k: [[d, labels[d]] for d in v] for k, v in ev.items()}})
    days = days_override or ev
    rows = []
    rng = np.random.default_rng(seed)
    for split, idx in days.items():
        for d in idx:
            rows.append({"day": d, "label": labels[d], "split": split, "sr_mean": float(rng.uniform(0.5, 0.9)),
                         "energy_kj_per_slot": 1616.0, "energy_efficiency": 0.3, "jain": 0.8,
                         "plan_ms_per_slot": 1.0, "obs_spec_hash": obs_hash or obs_spec_hash(grid, scenario),
                         "eval_days_hash": eval_hash, "scenario_hash": scenario.hash(), "seed": seed,
                         "method": method, "dataset": ds, "profile": cfg["profile"]})
    run = root / "results" / ds / method / f"seed{seed}"
    run.mkdir(parents=True, exist_ok=True)
    pl.DataFrame(rows).write_parquet(run / "days.parquet")
    init = initial_positions(t.demand[t.train_days].mean(axis=(0, 1)), grid, scenario.n_uavs,
                             scenario.init.kmeans_seed)
    traj = np.repeat(init[None, None], 144, axis=1).repeat(2, axis=0)  # (2 days, 144, K, 2)
    np.savez(run / "trajectory.npz", positions=traj, days=np.array([ev["id"][0], ev["ood"][0]]))
    for f in ("days.parquet", "trajectory.npz"):
        os.utime(run / f, (T0 + 20, T0 + 20))
    return run / "days.parquet"


def write_training(cfg: dict, root: Path, ds: str, method: str, seed: int, *, days: list[int] | None = None) -> Path:
    """Writes checkpoint.pt and train_manifest.json of one learning job (training days only by default)."""
    from prep.tensor import load

    t = load(root / "results" / "data" / ds)
    train = list(map(int, t.train_days))
    days = days if days is not None else train + train[:2]
    run = root / "results" / ds / method / f"seed{seed}"
    run.mkdir(parents=True, exist_ok=True)
    ckpt = run / "checkpoint.pt"
    ckpt.write_bytes(b"fixture checkpoint " + method.encode())
    os.utime(ckpt, (T0, T0))
    manifest = {"days": days, "day_labels": [t.labels[d] for d in days], "transitions_per_day_episode": 143,
                "n_transitions": 143 * len(days), "steps": 10, "data_files_read": [f"results/data/{ds}/demand.parquet"],
                "checkpoint": str(ckpt.relative_to(root)),
                "checkpoint_written_at": dt.datetime.fromtimestamp(T0, dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
                "read_test_data": False}
    path = run / "train_manifest.json"
    path.write_text(json.dumps(manifest, indent=2))
    os.utime(path, (T0 + 10, T0 + 10))
    return path


def calibrate(cfg: dict, root: Path) -> None:
    """Sets the calibration target to Static's training-day served ratio at the configured u and writes the
    record results/calibration/<dataset>.json (the fixture's stand-in for the calibrate rule)."""
    from audits.context import AuditContext
    from audits.derived import static_served_ratio

    ds = cfg["calibration"]["dataset"]
    ctx = AuditContext(root=root, config=cfg)
    train = ctx.train_index(ds)
    sr = static_served_ratio(ctx, ds, train, cfg["scenario"]["demand_intensity"])
    cfg["calibration"]["target_served_ratio"] = round(sr, 4)
    rec = {"dataset": ds, "days": list(map(int, train)), "u": cfg["scenario"]["demand_intensity"], "sr": sr}
    (root / "results" / "calibration").mkdir(parents=True, exist_ok=True)
    (root / "results" / "calibration" / f"{ds}.json").write_text(json.dumps(rec))


def build_clean_tree(root: Path | str) -> dict:
    """Builds the whole clean tree under `root`; returns the config it was built under."""
    root = Path(root)
    cfg = fixture_config()
    rng = np.random.default_rng(0)
    _milan_raw(cfg, root / "results" / "raw" / "milan" / "demo", rng)
    _yjmob_raw(cfg, root / "results" / "raw" / "yjmob" / "demo", rng)
    prepare(cfg, root)
    for ds in cfg["profiles"]["smoke"]["datasets"]:
        for method in METHODS:
            write_results(cfg, root, ds, method, 0)
            if method == "dswm":
                write_training(cfg, root, ds, method, 0)
    calibrate(cfg, root)
    (root / "config.json").write_text(json.dumps(cfg))
    return cfg
