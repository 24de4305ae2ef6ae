"""A small clean pipeline tree for testing and demonstrating the audit.

`build_clean_tree(root)` writes, under `root`, what the pipeline would have produced on two tiny datasets:
raw files in the published Milan and YJMob formats (results/raw/...), the prepared tensors made by the real
`prep` functions (results/data/...), per-day result files of static, greedy and two learning methods that share
one training (dswm trains; dswm_wo_unc evaluates its model), each with the model record and the method record
(resolved settings and BCD search) an evaluation stores and the content record (eval_manifest.json) it writes
last, the training manifest and checkpoint, trajectories and the calibration record. Test days carry more demand
than training days, so every training statistic differs from its all-days and test-segment values.

The tree's config is the repository's config.yaml shrunk (`fixture_config`), written as config.json; its
settings are resolved once from that mapping (`dswm.settings.resolve`) and every writer here reads them typed.
"""
from __future__ import annotations

import copy
import csv
import datetime as dt
import gzip
import json
import os
import shutil
from pathlib import Path
from zoneinfo import ZoneInfo

import numpy as np
import polars as pl
import pytest
import yaml

from dswm.settings import Settings, resolve
from prep.config import MilanConfig, YJMobConfig

REPO = Path(__file__).resolve().parents[1]
METHODS = ["static", "greedy", "dswm", "dswm_wo_unc"]
T0 = 1_700_000_000.0
"""File times of the fixture (seconds since the epoch): checkpoint, then manifest, then results."""


def fixture_config() -> dict:
    """The repository's config.yaml shrunk to a 5x5 Milan crop and a 5x5 YJMob crop on a 12x12 grid."""
    cfg = copy.deepcopy(yaml.safe_load((REPO / "config.yaml").read_text()))
    cfg["profile"] = "smoke"
    cfg["profiles"]["smoke"] = {"datasets": ["milan", "yjmob"], "seeds": {"milan": [0], "yjmob": [0]},
                                "eval_days": {"id": None, "ood": None}}
    cfg["methods"]["run"] = list(METHODS)
    cfg["scenario"]["demand_intensity"] = 1000.0  # the tiny crops need a larger u for Static to serve ~0.8
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


def _milan_raw(m: MilanConfig, out: Path, rng: np.random.Generator) -> list[Path]:
    """Daily Milan files (tab-separated, no header, blank = no activity) for the crop's squares; test days are
    busier, the more so the further east (so the all-days mean map differs in shape from the training one)."""
    crop, tz = m.crop, ZoneInfo(m.timezone)
    ids = [(crop.first_row + r) * m.full_cols + crop.first_col + c + 1
           for r in range(crop.rows) for c in range(crop.cols)]
    base = rng.gamma(2.0, 50.0, len(ids))
    east = np.array([c for r in range(crop.rows) for c in range(crop.cols)]) / max(crop.cols - 1, 1)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for seg, factor in ((m.split.train, 1.0), (m.split.test, 1.7)):
        a, b = (dt.date.fromisoformat(s) for s in seg)
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


def _yjmob_raw(y: YJMobConfig, out: Path, rng: np.random.Generator) -> Path:
    """yjmob100k-dataset1.csv.gz: period-5 activity (phase 4 low), busier test days, some masked rows, and a
    test-period-only hotspot in the north-east that would move a crop chosen on all days."""
    first_test = int(y.split.test[0])
    out.mkdir(parents=True, exist_ok=True)
    path = out / "yjmob100k-dataset1.csv.gz"
    with gzip.open(path, "wt", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["uid", "d", "t", "x", "y"])
        for uid in range(300):
            home = np.clip(np.round(rng.normal(6, 1.5, 2)), 1, y.full_size).astype(int)
            for d in range(y.n_days):
                lam = 8.0 * (0.3 if d % 5 == 4 else 1.0) * (1.6 if d >= first_test else 1.0)
                for _ in range(rng.poisson(lam)):
                    x, yy = np.clip(home + np.round(rng.normal(0, 1.5, 2)), 1, y.full_size).astype(int)
                    w.writerow([uid, d, int(rng.integers(0, 48)), int(x), int(yy)])
            if uid % 10 == 0:
                w.writerow([uid, y.n_days - 1, 5, 999, 999])
        for uid in range(300, 400):  # visitors of a north-east venue during the test period only
            for d in range(first_test, y.n_days):
                for _ in range(rng.poisson(60.0)):
                    x, yy = np.clip(np.round(rng.normal(10, 1.0, 2)), 1, y.full_size).astype(int)
                    w.writerow([uid, d, int(rng.integers(0, 48)), int(x), int(yy)])
    return path


def prepare(settings: Settings, root: Path, *, only: str | None = None) -> None:
    """Writes results/data/<dataset>/demand.parquet + meta.json with the prepare rule's own function.

    Args:
        settings: the fixture's settings; root: the tree; only: prepare this dataset alone.
    """
    from prep.pipeline import prepare_dataset

    common = settings.datasets.common
    ref = common.kappa_reference
    for name in sorted(settings.run.datasets, key=lambda d: d != ref):  # the kappa reference first
        if only is not None and name != only:
            continue
        prepare_dataset(getattr(settings.datasets, name), common, name,
                        raw=[str(root / "results" / "raw" / name / "demo")], out_dir=root / "results" / "data" / name,
                        reference_meta=None if name == ref else str(root / "results" / "data" / ref / "meta.json"))


def _limits(settings: Settings) -> dict[str, int | None]:
    """Days per split the profile keeps, as the evaluation takes them."""
    return {"id": settings.run.eval_days.id, "ood": settings.run.eval_days.ood}


def _hashes(settings: Settings, root: Path, ds: str):
    from dswm.protocol.evaluation import eval_days, result_hashes
    from dswm.sim.core import Grid
    from prep.tensor import load

    scenario = settings.scenario
    t = load(root / "results" / "data" / ds)
    grid = Grid(rows=t.grid.rows, cols=t.grid.cols, cell_m=t.grid.cell_m)
    ev = eval_days(t, _limits(settings))
    return scenario, t, grid, ev, result_hashes(ds, grid, scenario, ev, t.labels)


def evaluate_static(settings: Settings, root: Path, ds: str, seed: int) -> Path:
    """Evaluates Static with the pipeline's own evaluation (dswm.protocol.evaluation) and writes its result
    files."""
    from dswm.methods.classical import StaticController
    from dswm.protocol.evaluation import evaluate, write_days

    scenario, t, _, _, _ = _hashes(settings, root, ds)
    res = evaluate(tensor=t, controller=StaticController(name="static", seed=seed), scenario=scenario, seed=seed,
                   limits=_limits(settings), profile=settings.profile, device=settings.evaluation.device,
                   batch_days=settings.evaluation.batch_days, progress_interval_s=60.0)
    run = root / "results" / ds / "static" / f"seed{seed}"
    run.mkdir(parents=True, exist_ok=True)
    write_days(res.days, run / "days.parquet", model_record(settings, root, ds, "static", seed),
               method_record(settings, "static", seed))
    np.savez(run / "trajectory.npz", **res.trajectories)
    write_record(run)
    return run / "days.parquet"


def write_record(run: Path) -> None:
    """Writes the content record the evaluate job writes last (`dswm.protocol.evaluation.write_eval_record`) for
    the result files of `run`, and gives all three the fixture's result time."""
    from dswm.protocol.evaluation import EVAL_OUTPUTS, EVAL_RECORD_FILE, write_eval_record

    write_eval_record(run / EVAL_RECORD_FILE, {name: run / name for name in EVAL_OUTPUTS})
    for f in (*EVAL_OUTPUTS, EVAL_RECORD_FILE):
        os.utime(run / f, (T0 + 20, T0 + 20))


def model_record(settings: Settings, root: Path, ds: str, method: str, seed: int) -> dict:
    """The model record a clean evaluation of `method` stores in days.parquet (as
    `dswm.pipeline.setup.model_record`): for a learning method, its training source's model.pt (already written)
    with its SHA-256 and manifest."""
    from prep.rawio import sha256_file

    source = settings.training_sources().get(method)
    if source is None:
        return {"method": method, "train_source": None, "model": None, "model_sha256": None, "train_manifest": None}
    run = Path("results") / ds / source / f"seed{seed}"
    return {"method": method, "train_source": source, "model": (run / "model.pt").as_posix(),
            "model_sha256": sha256_file(root / run / "model.pt"),
            "train_manifest": (run / "train_manifest.json").as_posix()}


def method_record(settings: Settings, method: str, seed: int = 0) -> dict:
    """The method record a clean evaluation of `method` stores in days.parquet: built by the evaluate job's own
    `dswm.pipeline.setup.method_record` from the method's settings and the controller they build."""
    from dswm.methods import registry
    from dswm.pipeline.setup import method_record as job_method_record

    m = settings.methods[method]
    ctrl = registry.build(method, target=m.target, options=m.options, seed=seed, device=settings.evaluation.device)
    return job_method_record(m, ctrl)


def write_results(settings: Settings, root: Path, ds: str, method: str, seed: int, *, obs_hash: str | None = None,
                  days_override: dict[str, list[int]] | None = None, init_pos: np.ndarray | None = None,
                  record: dict | None = None, settings_record: dict | None = None) -> Path:
    """Writes days.parquet and trajectory.npz of one job in the evaluation's format, with the hashes, model
    record and method record a clean evaluation records (or the planted `obs_hash`, evaluated `days_override`,
    initial positions `init_pos`, model `record`, method `settings_record`)."""
    from dswm.protocol.evaluation import DAY_COLUMNS, write_days
    from dswm.sim.core import initial_deployment

    scenario, t, grid, ev, hashes = _hashes(settings, root, ds)
    if obs_hash is not None:
        hashes["obs_spec_hash"] = obs_hash
    days = days_override or ev
    rng = np.random.default_rng(seed)
    rows = [{"day": d, "label": t.labels[d], "split": split, "sr_mean": float(rng.uniform(0.5, 0.9)),
             "energy_kj_per_slot": 1616.0, "energy_efficiency": 0.3, "jain": 0.8, "plan_ms_per_slot": 1.0,
             **hashes, "seed": seed, "method": method, "dataset": ds, "profile": settings.profile,
             "data_source": "demo"} for split, idx in days.items() for d in idx]
    run = root / "results" / ds / method / f"seed{seed}"
    run.mkdir(parents=True, exist_ok=True)
    write_days(pl.DataFrame(rows).select(DAY_COLUMNS), run / "days.parquet",
               record if record is not None else model_record(settings, root, ds, method, seed),
               settings_record if settings_record is not None else method_record(settings, method, seed))
    init = initial_deployment(t, grid, scenario) if init_pos is None else init_pos
    traj = {}
    for split in ("id", "ood"):
        path = np.repeat(init[None], scenario.slots_per_day, axis=0).astype(np.float32)  # (T, K, 2)
        traj.update({f"{split}_pos": path, f"{split}_status": np.zeros(path.shape[:2], dtype=np.int64),
                     f"{split}_day": np.int64(ev[split][0]), f"{split}_label": np.str_(t.labels[ev[split][0]])})
    np.savez(run / "trajectory.npz", **traj)
    write_record(run)
    return run / "days.parquet"


def write_training(root: Path, ds: str, method: str, seed: int, *, days: list[int] | None = None) -> Path:
    """Writes what the train rule leaves for a learning job: train/checkpoint.pt, model.pt and
    train_manifest.json (recording training days only unless `days` is given), in that order in time. The
    manifest records the SHA-256 of both files and of the prepared tensor and meta.json, as
    `dswm.pipeline.jobs.train_job` does."""
    from prep.atomic import write_json
    from prep.rawio import sha256_file
    from prep.tensor import META_FILE, TENSOR_FILE, load

    data_dir = root / "results" / "data" / ds
    data_files = [{"path": f"results/data/{ds}/{name}", "sha256": sha256_file(data_dir / name)}
                  for name in (TENSOR_FILE, META_FILE)]
    t = load(data_dir)
    train = list(map(int, t.train_days))
    days = days if days is not None else train + train[:2]
    run = root / "results" / ds / method / f"seed{seed}"
    (run / "train").mkdir(parents=True, exist_ok=True)
    ckpt, model = run / "train" / "checkpoint.pt", run / "model.pt"
    ckpt.write_bytes(b"fixture checkpoint " + method.encode())
    model.write_bytes(b"fixture model " + method.encode())
    os.utime(ckpt, (T0, T0))
    os.utime(model, (T0 + 5, T0 + 5))
    manifest = {"days": days, "day_labels": [t.labels[d] for d in days], "transitions_per_day_episode": 143,
                "n_transitions": 143 * len(days), "steps": 10, "data_files_read": data_files,
                "checkpoint": str(ckpt.relative_to(root)), "checkpoint_sha256": sha256_file(ckpt),
                "checkpoint_written_at": dt.datetime.fromtimestamp(T0, dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
                "read_test_data": False, "model": str(model.relative_to(root)), "model_sha256": sha256_file(model)}
    path = run / "train_manifest.json"
    write_json(path, manifest)
    os.utime(path, (T0 + 10, T0 + 10))
    return path


def calibrate(settings: Settings, root: Path) -> float:
    """The fixture's calibration: Static's training-day score at the configured u (dswm.protocol.calibration),
    written in the calibrate rule's format; returns it rounded, the target the fixture's config records."""
    from dswm.protocol.calibration import static_score
    from prep.tensor import load

    ds = settings.calibration.dataset
    t = load(root / "results" / "data" / ds)
    scenario = settings.scenario
    sr = static_score(t, scenario, t.train_days)
    rec = {"demand_intensity": scenario.demand_intensity, "served_ratio": sr, "target": round(sr, 4),
           "iterations": 0, "dataset": ds, "data_source": t.meta["source"],
           "train_days": [t.labels[d] for d in t.train_days], "config_value": scenario.demand_intensity}
    (root / "results" / "calibration").mkdir(parents=True, exist_ok=True)
    (root / "results" / "calibration" / "demand_intensity.json").write_text(json.dumps(rec))
    return round(sr, 4)


def build_clean_tree(root: Path | str) -> Settings:
    """Builds the whole clean tree under `root`, its config written as `root`/config.json.

    Returns:
        The settings resolved from that config (what the audit of the tree reads).
    """
    root = Path(root)
    cfg = fixture_config()
    settings = resolve(cfg)
    rng = np.random.default_rng(0)
    _milan_raw(settings.datasets.milan, root / "results" / "raw" / "milan" / "demo", rng)
    _yjmob_raw(settings.datasets.yjmob, root / "results" / "raw" / "yjmob" / "demo", rng)
    prepare(settings, root)
    for ds in settings.run.datasets:
        for method in settings.methods:
            if method == "dswm":  # the training source; dswm_wo_unc evaluates its model
                write_training(root, ds, method, 0)
            if method == "static":
                evaluate_static(settings, root, ds, 0)
            else:
                write_results(settings, root, ds, method, 0)
    cfg["calibration"]["target_served_ratio"] = calibrate(settings, root)
    (root / "config.json").write_text(json.dumps(cfg))
    return resolve(cfg)


@pytest.fixture(scope="module", autouse=True)
def one_torch_thread():
    """The fixture's environments are tiny (25 cells): one thread is fastest, and no worse on a busy machine.
    Autouse in every module that imports it."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    """The clean tree, built once per module: (its root, its settings)."""
    root = tmp_path_factory.mktemp("clean")
    return root, build_clean_tree(root)


@pytest.fixture
def tree(clean, tmp_path):
    """A private copy of the clean tree (file times kept) and its settings."""
    root, settings = clean
    dst = tmp_path / "tree"
    shutil.copytree(root, dst)
    return dst, settings
