"""The sample-efficiency probe (paper Fig. 9): snapshots taken in the main training leave it unchanged and record the
budget and the transitions; a checkpoint whose run took other snapshots (or none) is not continued; a train job's
slice asks for snapshots only for the probed jobs; the audit's ``protocol.probes_out_of_tables`` passes a clean tree
with probe files and fails when a probe number is copied into a table's source; the figure's numbers."""
from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import polars as pl
import pytest
import torch
import yaml

from audit_fixtures import clean, one_torch_thread, write_record  # noqa: F401 (fixtures)
from dswm import settings as S
from dswm.figures.common import read_csv
from dswm.figures.sample_efficiency import draw_sample_efficiency
from dswm.methods.maddpg import MADDPGController, MADDPGSettings
from dswm.methods.snapshots import INDEX_FILE, Snapshots, SnapshotError, export, read_index
from dswm.protocol.probe import PROBE_SPLIT, probe_path
from learner_checks import core, scenario3  # noqa: F401 (fixtures)

ROOT = Path(__file__).resolve().parents[1]
# Two day-episodes (the budget's units), 43 gradient steps: a learner that trains in a few seconds.
TINY = MADDPGSettings(crop_radius=1, index_embed=4, actor_hidden=16, actor_depth=2, critic_hidden=32, critic_depth=2,
                      actor_lr=1e-3, critic_lr=1e-3, gamma=0.5, tau=0.05, noise_std=0.2, action_reg=1e-3,
                      grad_clip=1.0, buffer_size=1000, batch_size=32, warmup=200, transitions=2 * 143,
                      update_every=2, gradient_steps=1, log_points=10, checkpoint_every=1, matmul_dtype="float32")
FRACTIONS = (0.25, 0.5, 1.0)


def weights(path) -> dict[str, torch.Tensor]:
    """Every tensor of a MADDPG model file, by "<network>.<parameter>"."""
    blob = torch.load(path, map_location="cpu", weights_only=False)
    return {f"{k}.{p}": t for k in ("actor", "critic") for p, t in blob[k].items()}


def same_weights(a, b) -> bool:
    wa, wb = weights(a), weights(b)
    return wa.keys() == wb.keys() and all(torch.equal(wa[k], wb[k]) for k in wa)


@pytest.fixture(scope="module")
def runs(core, tmp_path_factory):
    """The same seed trained twice: without snapshots (run "plain") and with them (run "snap")."""
    torch.set_num_threads(1)
    base = tmp_path_factory.mktemp("runs")
    plain = MADDPGController(name="maddpg", seed=0, options=TINY)
    plain.fit(core, run_dir=base / "plain")
    plain.save(base / "plain.pt")
    snaps = Snapshots(fractions=FRACTIONS, store=base / "snap" / "snapshots", key="run-key")
    snap = MADDPGController(name="maddpg", seed=0, options=TINY)
    snap.fit(core, run_dir=base / "snap", snapshots=snaps)
    snap.save(base / "snap.pt")
    return base, snaps


def test_snapshots_leave_training_unchanged_and_record_the_budget(runs, tmp_path):
    base, snaps = runs
    assert same_weights(base / "plain.pt", base / "snap.pt")  # the same model with and without snapshots
    got = [(e["fraction"], e["done"], e["total"], e["n_transitions"]) for e in snaps.entries()]
    # 1/4 and 1/2 of two day-episodes are both reached after the first one (143 transitions): one snapshot
    assert got == [(0.25, 1, 2, 143), (0.5, 1, 2, 143), (1.0, 2, 2, 286)]
    first, final = (base / "snap" / "snapshots" / e["file"] for e in snaps.entries()[1:])
    assert same_weights(final, base / "snap.pt") and not same_weights(first, final)
    index = export(snaps, tmp_path / "out", method="maddpg", seed=0)
    assert [e["file"] for e in read_index(tmp_path / "out")] == [e["file"] for e in index["snapshots"]]
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == [INDEX_FILE, "snapshot_1of2.pt",
                                                                    "snapshot_2of2.pt"]
    assert (tmp_path / "out" / "snapshot_2of2.pt").samefile(base / "snap" / "snapshots" / "snapshot_2of2.pt")
    loaded = MADDPGController(name="maddpg", seed=0, options=TINY)
    loaded.load(tmp_path / "out" / "snapshot_1of2.pt")  # a snapshot is a loadable model file
    (tmp_path / "out" / "snapshot_1of2.pt").unlink()
    with pytest.raises(SnapshotError, match="snapshot_1of2.pt: missing or changed"):
        read_index(tmp_path / "out")
    assert snaps.entries()[0]["file"] == "snapshot_1of2.pt"  # the store keeps its own
    assert export(None, tmp_path / "empty", method="maddpg", seed=0) is None
    assert list((tmp_path / "empty").iterdir()) == []  # a job that takes none leaves its output empty


def test_a_run_resumes_only_a_checkpoint_whose_run_took_the_same_snapshots(runs, core):
    base, snaps = runs
    ckpt = base / "snap" / "checkpoint.pt"
    before = ckpt.stat().st_mtime_ns
    again = Snapshots(fractions=FRACTIONS, store=base / "snap" / "snapshots", key="run-key")
    MADDPGController(name="maddpg", seed=0, options=TINY).fit(core, run_dir=base / "snap", snapshots=again)
    assert ckpt.stat().st_mtime_ns == before  # the finished run was continued: nothing trained, nothing rewritten
    assert [e["sha256"] for e in again.entries()] == [e["sha256"] for e in snaps.entries()]
    # The plain run's finished checkpoint took no snapshot: it is removed and the run trains afresh.
    fresh = Snapshots(fractions=(0.5, 1.0), store=base / "plain" / "snapshots", key="run-key")
    MADDPGController(name="maddpg", seed=0, options=TINY).fit(core, run_dir=base / "plain", snapshots=fresh)
    assert [(e["fraction"], e["n_transitions"]) for e in fresh.entries()] == [(0.5, 143), (1.0, 286)]
    assert same_weights(base / "plain" / "snapshots" / fresh.entries()[1]["file"], base / "plain.pt")


def test_only_the_probed_train_jobs_take_snapshots():
    cfg = yaml.safe_load((ROOT / "config.yaml").read_text())
    cfg["profile"] = "demo"
    cfg["figures"]["budgets"]["demo"]["seeds"] = [1]
    cfg["figures"]["sample_efficiency"]["methods"] = ["dswm", "dswm_wo_unc", "ppo", "greedy"]
    settings = S.resolve(cfg)
    assert S.probed_methods(settings) == ["dswm", "ppo"]  # dswm_wo_unc evaluates dswm's model; greedy learns nothing
    assert S.probe_jobs(settings) == [("milan", "dswm", 1), ("milan", "ppo", 1)]
    fractions = cfg["figures"]["sample_efficiency"]["fractions"]
    assert S.train_slice(settings, "ppo", "milan", 1)["snapshots"] == {"fractions": fractions}
    plain = S.train_slice(settings, "ppo")
    for other in (("milan", 0), ("shanghai", 1)):
        assert S.train_slice(settings, "ppo", *other) == plain  # other jobs' slices (and reruns) are unchanged
    assert "eval_days" not in S.probe_slice(settings, "ppo")


def test_the_probe_job_scores_each_snapshot_on_the_first_id_day_as_the_evaluation_scores_the_model(
        runs, scenario3, tmp_path):
    """A tensor whose first ID test day is day 3, the snapshots of ``runs``: the probe file holds one marked row per
    fraction, and the trained model's row is what the evaluation (ID and OOD days batched) scores on day 3."""
    from dswm.config import to_plain
    from dswm.pipeline import tracking
    from dswm.pipeline.probe import probe_job
    from dswm.protocol.evaluation import evaluate
    from dswm.settings import Display, MethodSettings
    from dswm.sim.env import synthetic_demand
    from prep.tensor import load, write

    base, snaps = runs
    demand = synthetic_demand(days=6, rows=6, cols=6, slots=scenario3.slots_per_day, seed=4).astype(np.float32)
    meta = {"dataset": "toy", "source": "demo", "slots_per_day": scenario3.slots_per_day, "kappa": 1.0,
            "train_mean_normalized": 0.1, "grid": {"rows": 6, "cols": 6, "cell_m": 235.0},
            "days": [{"index": i, "label": f"d{i}", "split": "train" if i < 3 else "test"} for i in range(6)],
            "eval_days": {"id": [3, 4], "ood": [5]}}
    write(tmp_path / "data", demand, meta)
    export(snaps, tmp_path / "snapshots", method="maddpg", seed=0)
    mlflow = {"store": str(tmp_path / "mlflow.db"), "artifacts": str(tmp_path / "mlartifacts"),
              "experiment": "probe", "batch_size": 50}
    tracking.init_store(store=mlflow["store"], artifacts=mlflow["artifacts"], experiment=mlflow["experiment"])
    method = MethodSettings(name="maddpg", target="dswm.methods.maddpg:MADDPGController", label="MADDPG",
                            table_class="MARL", learns=True, training_source="maddpg", options=TINY)
    job = {"profile": "smoke", "scenario": to_plain(scenario3), "mlflow": {"experiment": "probe"},
           "method": to_plain(method),
           "evaluation": {"device": "cpu", "torch_threads": 1, "batch_days": True, "reuse_seed_independent": False}}
    model = MADDPGController(name="maddpg", seed=0, options=TINY)
    model.load(base / "snap.pt")
    ev = evaluate(tensor=load(tmp_path / "data"), controller=model, scenario=scenario3, seed=0,
                  limits={"id": None, "ood": None}, profile="smoke", device="cpu", batch_days=True,
                  progress_interval_s=60.0).days
    ev.write_parquet(tmp_path / "days.parquet")
    out = tmp_path / "probes" / "probe.parquet"
    frame = probe_job(job=job, mlflow_cfg=mlflow, display=Display(progress_mininterval_s=60.0),
                      tensor_dir=tmp_path / "data", dataset="toy", method="maddpg", seed=0,
                      snapshots_dir=tmp_path / "snapshots",
                      evaluation=tmp_path / "days.parquet", out=out,
                      record_out=tmp_path / "probes" / "probe_manifest.json", repo=ROOT)
    assert frame.equals(pl.read_parquet(out))
    assert frame["fraction"].to_list() == list(FRACTIONS) and frame["n_transitions"].to_list() == [143, 143, 286]
    assert set(frame["day"]) == {3} and set(frame["split"]) == {PROBE_SPLIT} and frame["probe"].all()
    assert frame["final"].to_list() == [False, False, True]
    assert frame["sr_mean"][0] == frame["sr_mean"][1] != frame["sr_mean"][2]  # 1/4 and 1/2: the same snapshot
    on_day = ev.filter(pl.col("day") == 3)["sr_mean"][0]
    assert frame["evaluated_sr_mean"].to_list() == [on_day] * 3 and frame["sr_mean"][2] == on_day


# ---- the audit -------------------------------------------------------------------------------------------------
def probe_rows(days: pl.DataFrame, day: int, values: dict[float, float]) -> pl.DataFrame:
    """Probe rows of ``days``' job on ``day``, one per {fraction: sr_mean}, in the probe job's format (the job's
    evaluated value on ``day`` recorded beside each)."""
    row = days.filter(pl.col("day") == day).row(0, named=True)
    return pl.DataFrame([{**row, "split": PROBE_SPLIT, "sr_mean": sr, "probe": True, "fraction": f,
                          "fraction_done": f, "done": int(4 * f), "total": 4, "n_transitions": int(572 * f),
                          "final": f == 1.0, "snapshot": f"snapshot_{int(4 * f)}of4.pt", "snapshot_sha256": "0" * 64,
                          "evaluated_sr_mean": row["sr_mean"]} for f, sr in values.items()])


@pytest.fixture
def probed(clean, tmp_path):
    """A copy of the clean tree with a probe file of milan/dswm/seed0: a checkpoint at half the budget scoring
    0.4321 on the first ID day, and the trained model scoring what dswm's evaluation recorded that day."""
    from audits.context import AuditContext

    root, settings = clean
    dst = tmp_path / "tree"
    shutil.copytree(root, dst)
    days = pl.read_parquet(dst / "results/milan/dswm/seed0/days.parquet")
    day = int(days.filter(pl.col("split") == "id")["day"][0])
    final = days.filter(pl.col("day") == day)["sr_mean"][0]
    path = dst / probe_path("milan", "dswm", 0)
    path.parent.mkdir(parents=True)
    probe_rows(days, day, {0.5: 0.4321, 1.0: final}).write_parquet(path)
    return dst, settings, day, lambda: AuditContext(root=dst, settings=settings)


def check(ctx):
    from audits.probes import check_probes_out_of_tables

    return check_probes_out_of_tables(ctx)


def copy_into(root: Path, method: str, frame) -> Path:
    """Rewrite ``method``'s milan/seed0 result file with ``frame(days)`` and re-record its content record."""
    from dswm.protocol.evaluation import read_method_record, read_model_record, write_days

    run = root / "results" / "milan" / method / "seed0"
    days = run / "days.parquet"
    model, settings = read_model_record(days), read_method_record(days)
    write_days(frame(pl.read_parquet(days)), days, model, settings)
    write_record(run)
    return days


def test_a_clean_run_with_and_without_probes_passes(clean, probed):
    from audits.context import AuditContext

    root, settings = clean
    bare = check(AuditContext(root=root, settings=settings))
    assert bare.passed and bare.evidence["probe_files"] == [] and "no probe file" in bare.evidence["note"]
    chk = check(probed[3]())
    assert chk.passed, chk.failures
    assert chk.evidence["probe_files"] == [probe_path("milan", "dswm", 0)] and chk.evidence["probe_rows"] == 2
    assert chk.evidence["rows_equal_to_their_evaluation"] == [f"{probe_path('milan', 'dswm', 0)} fraction 1.0"]


def test_the_tables_audit_leaves_the_probe_files_to_the_probe_audit(probed):
    """The workflow's two reports: the tables' (audit_report) reads no probe file, so its inputs stay those of
    `tables` once `figures` has written probes; the probe report (audit_probes) reads them and the tables' sources,
    and turns red on a probe number copied into one."""
    from audits.probes import PROBES_LEFT_OUT
    from audits.runner import run_audit

    root, settings, day, _ = probed
    tables = run_audit(root=root, settings=settings, scope="tables")
    probe = probe_path("milan", "dswm", 0)
    assert tables["passed"] and tables["scope"] == "tables"
    assert probe not in [f["path"] for f in tables["read_only"]["files"]]
    (chk,) = [c for c in tables["checks"] if c["id"] == "protocol.probes_out_of_tables"]
    assert chk["evidence"]["probe_files"] == [] and chk["evidence"]["note"] == PROBES_LEFT_OUT
    probes = run_audit(root=root, settings=settings, scope="probes")
    assert probes["passed"] and [c["id"] for c in probes["checks"]] == ["protocol.probes_out_of_tables",
                                                                        "read-only.unchanged"]
    read = [f["path"] for f in probes["read_only"]["files"]]
    assert probe in read and "results/milan/greedy/seed0/days.parquet" in read
    copy_into(root, "greedy", lambda d: d.with_columns(
        pl.when(pl.col("day") == day).then(pl.lit(0.4321)).otherwise(pl.col("sr_mean")).alias("sr_mean")))
    red = run_audit(root=root, settings=settings, scope="probes")
    assert not red["passed"] and red["checks"][0]["failures"][0].startswith(
        "results/milan/greedy/seed0/days.parquet: day ")
    with pytest.raises(ValueError, match="audit scope 'probe': expected one of all, tables, probes, learning, extra"):
        run_audit(root=root, settings=settings, scope="probe")


def test_a_checkpoints_probe_value_copied_into_a_result_file_fails_naming_it(probed):
    root, _, day, ctx = probed
    days = copy_into(root, "dswm", lambda d: d.with_columns(
        pl.when(pl.col("day") == day).then(pl.lit(0.4321)).otherwise(pl.col("sr_mean")).alias("sr_mean")))
    chk = check(ctx())
    assert not chk.passed
    assert len(chk.failures) == 1
    assert chk.failures[0].startswith("results/milan/dswm/seed0/days.parquet: day ")
    assert "0.4321" in chk.failures[0] and "checkpoint at fraction 0.5 of the budget of dswm/seed0" in chk.failures[0]
    assert "results/probes/milan/dswm/seed0/probe.parquet" in chk.failures[0]
    assert days.is_file()


def test_probe_rows_appended_to_a_result_file_fail_by_their_marks(probed):
    root, _, day, ctx = probed
    probe = pl.read_parquet(root / probe_path("milan", "dswm", 0))
    copy_into(root, "dswm", lambda d: pl.concat([d, probe], how="diagonal_relaxed"))
    failures = check(ctx()).failures
    where = "results/milan/dswm/seed0/days.parquet"
    assert any(f.startswith(f"{where}: holds the probe column(s) ['probe', 'fraction'") for f in failures)
    assert any(f.startswith(f"{where}: 2 row(s) of split 'probe'") for f in failures)


def test_a_checkpoints_value_copied_into_another_methods_result_file_fails_and_the_trained_models_does_not(probed):
    root, _, day, ctx = probed
    final = pl.read_parquet(root / probe_path("milan", "dswm", 0)).filter(pl.col("final"))["sr_mean"][0]
    for method, value in (("greedy", 0.4321), ("dswm_wo_unc", final)):
        copy_into(root, method, lambda d: d.with_columns(
            pl.when(pl.col("day") == day).then(pl.lit(value)).otherwise(pl.col("sr_mean")).alias("sr_mean")))
    failures = check(ctx()).failures
    # the trained model's probe value is the evaluation's own number on that day, not a probe number
    assert len(failures) == 1 and failures[0].startswith("results/milan/greedy/seed0/days.parquet: day ")
    assert "the probe value of the checkpoint at fraction 0.5 of the budget of dswm/seed0" in failures[0]


def test_a_trained_models_probe_value_other_than_its_evaluations_is_a_probe_number(probed):
    """A planner whose random stream depends on the days stepped together scores the probe day alone otherwise than
    in its evaluation's batch: that value, copied into the job's own result file, fails."""
    root, _, day, ctx = probed
    path = root / probe_path("milan", "dswm", 0)
    probe = pl.read_parquet(path)
    probe.with_columns(pl.when(pl.col("final")).then(pl.col("sr_mean") + 0.01).otherwise(pl.col("sr_mean"))
                       .alias("sr_mean")).write_parquet(path)
    assert check(ctx()).passed
    value = pl.read_parquet(path).filter(pl.col("final"))["sr_mean"][0]
    copy_into(root, "dswm", lambda d: d.with_columns(
        pl.when(pl.col("day") == day).then(pl.lit(value)).otherwise(pl.col("sr_mean")).alias("sr_mean")))
    failures = check(ctx()).failures
    assert len(failures) == 1 and failures[0].startswith("results/milan/dswm/seed0/days.parquet: day ")
    assert "the probe value of the trained model of dswm/seed0" in failures[0]


# ---- the figure ------------------------------------------------------------------------------------------------
def test_the_figure_draws_mean_and_std_over_seeds_against_transitions(tmp_path):
    rows = [{"method": m, "seed": s, "fraction": f, "fraction_done": f, "n_transitions": n * f, "sr_mean": sr + s * d,
             "label": "2013-12-21", "dataset": "milan", "split": PROBE_SPLIT}
            for m, n, sr, d in (("ppo", 8000, 0.5, 0.02), ("dswm", 2860, 0.7, 0.0))
            for s in (0, 1) for f in (0.5, 1.0)]
    out = {k: tmp_path / f"sample_efficiency.{k}" for k in ("png", "pdf", "csv")}
    draw_sample_efficiency(pl.DataFrame(rows), order=["dswm", "ppo"], labels={"dswm": "DSWM", "ppo": "PPO"},
                           fractions=[0.5, 1.0], profile="demo", source="demo", out=out)
    assert all(p.stat().st_size > 0 for p in out.values())
    csv = read_csv(out["csv"])
    ppo = csv.filter((pl.col("method") == "ppo") & (pl.col("fraction") == 1.0)).row(0, named=True)
    assert ppo["n_transitions"] == 8000 and ppo["seeds"] == 2
    assert ppo["sr_mean"] == pytest.approx(0.51) and ppo["sr_mean_std"] == pytest.approx(0.02 / np.sqrt(2))
    header = out["csv"].read_text().splitlines()[0]
    assert header.startswith("# Paper Fig. 9 (sample_efficiency)") and "probe day 2013-12-21" in header
    assert "never in a table" in header
