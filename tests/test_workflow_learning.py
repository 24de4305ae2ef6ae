"""The learning curves (`snakemake learning`, config.yaml `learning`): the validation days are the last training days
and never a test day; the ladder, caps and slices as configured, the tables' slices untouched; the untrained
snapshot; the CSV's table; and the target itself on the smoke profile (marked integration: minutes)."""
from __future__ import annotations

import copy
import json
import re
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import polars as pl
import pytest
import yaml

from dswm import settings as S
from dswm.config import ConfigError
from dswm.figures.common import read_csv
from dswm.figures.learning import (CSV_COLUMNS, VERDICT_COLUMNS, curve_axis, curve_table, learning_verdict,
                                   return_rise, sr_learned, training_units)
from dswm.methods.snapshots import Snapshots, SnapshotError
from dswm.protocol.learning import learning_days

ROOT = Path(__file__).resolve().parents[1]
SCHEMA = ROOT / "workflow" / "schemas" / "config.schema.yaml"


def config(profile: str = "smoke") -> dict:
    with open(ROOT / "config.yaml", encoding="utf-8") as fh:
        return {**yaml.safe_load(fh), "profile": profile}


def resolved(cfg: dict):
    return S.resolve(cfg, schema=SCHEMA), S.learning_settings(cfg, cfg["profile"])


def fake_tensor(n_train=10, n_test=12, eval_id=(0, 1, 2), eval_ood=(3, 4, 10, 11)):
    """A stand-in of prep.tensor.DemandTensor: days 0..n_train-1 train, then the test days."""
    train = np.arange(n_train)
    test = np.arange(n_train, n_train + n_test)
    evals = {"id": np.array([test[i] for i in eval_id]), "ood": np.array([test[i] for i in eval_ood])}
    return SimpleNamespace(train_days=train, test_days=test, eval_days=lambda s: evals[s],
                           labels=[f"day{d:02d}" for d in range(n_train + n_test)], meta={"dataset": "milan"})


# ---- days and ladder ---------------------------------------------------------------------------------------------
def test_the_validation_days_are_the_last_training_days_and_the_run_trains_on_the_others():
    fit, val = learning_days(fake_tensor(), 3)
    assert fit == [0, 1, 2, 3, 4, 5, 6] and val == [7, 8, 9]


def test_too_many_validation_days_or_a_test_day_among_them_stops_with_the_day_named():
    with pytest.raises(ValueError, match=r"10 training day\(s\), but learning.validation_days = 10 needs at least 11"):
        learning_days(fake_tensor(), 10)
    leaky = fake_tensor()
    leaky.train_days = np.arange(11)  # day 10 is a test day as well: a broken split must not reach the scores
    with pytest.raises(ValueError, match=r"day day10 \(index 10\) is not a training day; .* never a test day"):
        learning_days(leaky, 2)


def test_the_configured_ladder_is_log_spaced_ends_at_the_cap_and_the_untrained_point_is_added():
    for profile in ("smoke", "demo", "paper"):
        _, learning = resolved(config(profile))
        ladder = np.array(learning.ladder)
        assert ladder[-1] == 1.0 and ladder[0] > 0
        assert np.allclose(np.diff(np.log2(ladder)), np.log2(ladder[1] / ladder[0]))  # log-spaced
    cfg = config("demo")
    assert S.learning_settings(cfg, "demo").ladder == (1 / 64, 1 / 32, 1 / 16, 1 / 8, 1 / 4, 1 / 2, 1.0)
    job = S.learning_train_slice(*resolved(cfg), "ppo")
    assert job["snapshots"] == {"fractions": [1 / 64, 1 / 32, 1 / 16, 1 / 8, 1 / 4, 1 / 2, 1.0], "untrained": True}
    assert job["validation_days"] == 3


def test_a_ladder_without_the_cap_or_a_zero_fraction_is_refused_naming_the_key():
    cfg = config()
    cfg["learning"]["budgets"]["smoke"]["ladder"] = [0.25, 0.5]
    with pytest.raises(ConfigError, match=r"key 'learning.ladder' \(profile 'smoke'\): expected distinct fractions of "
                                          r"the cap in \(0, 1\] ending at 1 \(the cap itself\), found \[0.25, 0.5\]"):
        S.learning_settings(cfg, "smoke")
    cfg["learning"]["budgets"]["smoke"]["ladder"] = [0.0, 1.0]
    with pytest.raises(ConfigError, match=r"learning.*ladder"):
        S.resolve(cfg, schema=SCHEMA)


# ---- caps and slices ---------------------------------------------------------------------------------------------
def test_a_cap_merges_over_the_profile_budget_and_a_bad_key_names_the_cap():
    settings, learning = resolved(config("demo"))
    job = S.learning_train_slice(settings, learning, "ppo")
    paper, _ = resolved(config("paper"))  # the issue: PPO's curve reaches its paper budget, 1,002,144 transitions
    assert job["method"]["options"]["day_episodes"] == paper.methods["ppo"].options.day_episodes == 7008
    assert job["method"]["options"]["n_envs"] == paper.methods["ppo"].options.n_envs == 16  # the cap's own
    assert S.learning_train_slice(settings, learning, "sac")["method"]["options"]["n_envs"] == 4  # the demo's own
    assert S.learning_train_slice(settings, learning, "dswm")["method"]["options"]["steps"] == 3200
    bad = config("demo")
    bad["learning"]["budgets"]["demo"]["caps"]["ppo"] = {"day_episode": 10}
    settings, learning = resolved(bad)
    with pytest.raises(ConfigError, match=r"key 'learning.caps.ppo'"):
        S.check_learning(settings, learning)
    stray = config("demo")
    stray["learning"]["budgets"]["demo"]["caps"]["greedy"] = {"sweeps": 1}
    with pytest.raises(ConfigError, match=r"key 'learning.caps' names 'greedy', which 'learning.methods' does not "
                                          r"list"):
        S.check_learning(*resolved(stray))


def test_start_order_ranks_the_jobs_longest_first_changes_no_job_and_a_stray_name_is_refused():
    settings, learning = resolved(config("demo"))
    learners = S.learning_methods(settings, learning)
    order = [m for m in learning.start_order if m in learners]
    ranks = [S.learning_priority(learning, learners, m) for m in order]
    assert ranks == list(range(len(order), 0, -1))  # the first listed highest, every listed one above 0
    assert S.learning_priority(learning, learners, "static") == 0  # a reference: after the listed ones
    other = config("demo")
    other["learning"]["budgets"]["demo"]["start_order"] = ["hrl_tpra"]
    reordered = S.learning_settings(other, "demo")
    assert S.learning_priority(reordered, learners, "hrl_tpra") == 1
    assert S.learning_priority(reordered, learners, order[0]) == 0
    for method in learners:  # scheduling only: the jobs read the same settings
        assert S.learning_train_slice(settings, learning, method) == S.learning_train_slice(settings, reordered, method)
    stray = config("demo")
    stray["learning"]["budgets"]["demo"]["start_order"] = ["ppo", "greedy"]
    with pytest.raises(ConfigError, match=r"key 'learning.start_order' names 'greedy', which 'learning.methods' does "
                                          r"not list"):
        S.check_learning(*resolved(stray))


def test_the_learning_section_changes_no_slice_of_the_tables_jobs():
    cfg = config("demo")
    other = copy.deepcopy(cfg)
    other["learning"]["budgets"]["demo"]["caps"]["ppo"] = {"day_episodes": 16}
    other["learning"]["validation_days"] = 2
    a, b = S.resolve(cfg, schema=SCHEMA), S.resolve(other, schema=SCHEMA)
    for method in a.trained():
        assert S.train_slice(a, method, "milan", 0) == S.train_slice(b, method, "milan", 0)
    assert S.audit_slice(a) == S.audit_slice(b) and S.evaluate_slice(a, "ppo") == S.evaluate_slice(b, "ppo")
    learners = S.learning_methods(a, S.learning_settings(cfg, "demo"))
    assert learners == ["dswm", "ppo", "sac", "maddpg", "ga_matr", "tdmpc", "hrl_tpra", "emorl_tcto"]
    assert S.learning_references(a, S.learning_settings(cfg, "demo")) == ["static", "greedy"]


# ---- the untrained snapshot --------------------------------------------------------------------------------------
def test_the_untrained_snapshot_comes_first_once_and_records_transitions_and_gradient_steps(tmp_path):
    snaps = Snapshots(fractions=(0.5, 1.0), store=tmp_path / "snapshots", key="k", untrained=True)
    snaps.claim(tmp_path / "ckpt.pt")
    state = {"v": b"init"}

    def write(path):
        path.write_bytes(state["v"])

    assert snaps.start(total=4, n_transitions=0, write=write) == [0.0]
    assert snaps.start(total=4, n_transitions=0, write=write) == []  # a resumed run does not take it again
    for done in (1, 2, 3, 4):
        state["v"] = f"after unit {done}".encode()
        snaps.step(done=done, total=4, n_transitions=143 * done, gradient_steps=10 * done, write=write)
    entries = snaps.entries()
    assert [e["fraction"] for e in entries] == [0.0, 0.5, 1.0] and snaps.requested() == (0.0, 0.5, 1.0)
    assert [(e["done"], e["n_transitions"], e["gradient_steps"]) for e in entries] == [(0, 0, 0), (2, 286, 20),
                                                                                      (4, 572, 40)]
    assert (tmp_path / "snapshots" / entries[0]["file"]).read_bytes() == b"init"
    without = Snapshots(fractions=(0.5, 1.0), store=tmp_path / "other", key="k")
    without.claim(tmp_path / "ckpt2.pt")
    assert without.start(total=4, n_transitions=0, write=write) == []
    with pytest.raises(SnapshotError, match="no snapshot at fraction 0.5"):
        without.entries()


# ---- the CSV -----------------------------------------------------------------------------------------------------
def score_rows(method, fraction, transitions, steps, srs, days=(7, 8, 9)):
    return pl.DataFrame({"method": method, "seed": 0, "dataset": "milan", "day": list(days),
                         "label": [f"day{d:02d}" for d in days], "sr_mean": list(srs), "split": "validation",
                         "fraction": fraction, "untrained": fraction == 0.0, "n_transitions": transitions,
                         "gradient_steps": steps})


def test_the_csv_has_a_row_per_snapshot_with_the_references_on_the_same_days():
    scores = pl.concat([score_rows("ppo", 0.0, 0, 0, (0.5, 0.6, 0.7)), score_rows("ppo", 0.5, 286, 20, (0.6, 0.7, 0.8)),
                        score_rows("ppo", 1.0, 572, 40, (0.7, 0.8, 0.9))])
    refs = pl.concat([score_rows("static", None, None, None, (0.7, 0.7, 0.7)),
                      score_rows("greedy", None, None, None, (0.8, 0.8, 0.9))])
    table = curve_table(scores, refs)
    assert tuple(table.columns) == CSV_COLUMNS
    assert table["transitions"].to_list() == [0, 286, 572] and table["untrained"].to_list() == [True, False, False]
    assert np.allclose(table["probe_sr"].to_numpy(), [0.6, 0.7, 0.8])
    assert table["static_sr"].to_list() == pytest.approx([0.7] * 3)
    assert set(table["greedy_sr"].round(6).to_list()) == {round((0.8 + 0.8 + 0.9) / 3, 6)}
    assert set(table["days"].to_list()) == {"day07;day08;day09"}
    assert curve_axis(table) == ("transitions", "environment transitions (log scale)")
    with pytest.raises(ValueError, match=r"learning curves: greedy \(fraction None\) was scored on \['day06', 'day07', "
                                         r"'day08'\], the others on \['day07', 'day08', 'day09'\]"):
        curve_table(scores, pl.concat([refs.filter(pl.col("method") == "static"),
                                       score_rows("greedy", None, None, None, (0.8,) * 3, days=(6, 7, 8))]))


def test_a_learner_whose_snapshots_share_their_transitions_is_drawn_against_its_gradient_steps():
    table = pl.DataFrame({"fraction": [0.0, 0.25, 0.5, 1.0], "untrained": [True, False, False, False],
                          "transitions": [1430, 1430, 1430, 1573], "gradient_steps": [0, 10, 20, 40]})
    assert curve_axis(table) == ("gradient_steps", "gradient steps (log scale; 1,430-1,573 transitions, pre-collected "
                                                   "ones included)")


# ---- the verdict (criterion 2 of the learning-curves issue) ------------------------------------------------------
def test_the_return_rises_only_by_more_than_twice_the_standard_error_of_its_tenths():
    noise = np.tile([-1.0, 1.0], 50)  # 100 units: tenths of 10, each with sample std ~1.05
    v = noise + np.linspace(0.0, 3.0, 100)
    first, last, rise, se = return_rise(v)
    assert (first, last) == pytest.approx((v[:10].mean(), v[-10:].mean())) and rise == pytest.approx(last - first)
    assert se == pytest.approx(np.sqrt(np.var(v[:10], ddof=1) / 10 + np.var(v[-10:], ddof=1) / 10)) and rise > 2 * se
    _, _, rise, se = return_rise(noise + np.linspace(0.0, 0.5, 100))  # rise 0.45 < 2 x 0.47
    assert not rise > 2 * se
    _, _, rise, _ = return_rise(np.linspace(5.0, 1.0, 100), falling=True)  # a loss that falls has risen
    assert rise == pytest.approx(4.0 * 90 / 99)  # tenths 90 of 99 steps of 4/99 apart
    assert return_rise([1.0, 2.0, 3.0])[3] == float("inf")  # one unit per tenth: no standard error, no verdict


def test_the_served_ratio_must_gain_5_points_unless_the_untrained_policy_already_serves_like_static():
    assert sr_learned(0.50, 0.55, static=0.70) and not sr_learned(0.50, 0.549, static=0.70)
    assert sr_learned(0.68, 0.68, static=0.70) and not sr_learned(0.68, 0.679, static=0.70)  # within 0.05 of Static
    assert not sr_learned(0.60, 0.64, static=None)


def test_repeated_and_seeded_values_are_not_units_of_the_learner_s_own():
    history = pl.DataFrame({"step": [10, 20, 30, 40, 50], "charts/episode_reward": [-9.0, -9.0, -5.0, -5.0, -4.0],
                            "charts/episode_return": [1.0, None, 2.0, float("nan"), 3.0]})
    assert training_units(history, "charts/episode_reward").rows() == [(30, -5.0), (50, -4.0)]  # pre-collection off
    assert training_units(history, "charts/episode_return").rows() == [(10, 1.0), (30, 2.0), (50, 3.0)]


def test_the_verdict_finds_the_first_snapshot_where_both_criteria_hold():
    scores = pl.concat([score_rows("ppo", f, int(f * 1000), int(f * 10), (sr,) * 3) for f, sr in
                        ((0.0, 0.50), (0.25, 0.52), (0.5, 0.56), (1.0, 0.60))]
                       + [score_rows("sac", f, int(f * 1000), int(f * 10), (sr,) * 3) for f, sr in
                          ((0.0, 0.50), (0.25, 0.60), (0.5, 0.60), (1.0, 0.49))])
    refs = pl.concat([score_rows("static", None, None, None, (0.7,) * 3),
                      score_rows("greedy", None, None, None, (0.8,) * 3)])
    steps = np.arange(1, 101) * 10
    rng = np.random.default_rng(0)
    histories = pl.concat([pl.DataFrame({"method": m, "seed": 0, "step": steps,
                                         "rollout/ep_rew_mean": np.linspace(-80.0, -60.0, 100) + rng.normal(0, 1, 100)})
                           for m in ("ppo", "sac")])
    verdict = learning_verdict(curve_table(scores, refs), histories)
    assert tuple(verdict.columns) == VERDICT_COLUMNS
    ppo, sac = (verdict.filter(pl.col("method") == m).row(0, named=True) for m in ("ppo", "sac"))
    assert ppo["return_rises"] and ppo["sr_learned"] and ppo["learned"]
    # 0.25: the return over its first 25 units rises, but the served ratio gained 0.02 only; 0.5: both hold
    assert (ppo["learned_at_fraction"], ppo["learned_at_transitions"], ppo["learned_at_gradient_steps"]) == (0.5, 500, 5)
    assert ppo["units"] == 100 and ppo["sr_gain"] == pytest.approx(0.10)
    assert sac["return_rises"] and not sac["sr_learned"] and not sac["learned"]  # it ends below where it started
    assert sac["learned_at_fraction"] == 0.25  # ... though it had learned at a quarter of its cap


# ---- the target --------------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def learning_run(tmp_path_factory):
    """A copy of the working tree where `snakemake learning --config profile=smoke` has run (from raw data)."""
    from smoke import copy_tree, run_smoke

    return run_smoke(copy_tree(tmp_path_factory.mktemp("learning") / "repo"), "learning", "learning")


@pytest.mark.integration
def test_the_learning_target_writes_a_curve_per_learner_on_the_validation_days(learning_run):
    cfg = config("smoke")
    settings, learning = resolved(cfg)
    csv = learning_run / "results" / "figures" / "learning_curves.csv"
    table = read_csv(csv)
    for ext in ("png", "pdf"):
        assert (csv.with_suffix(f".{ext}")).stat().st_size > 0
    learners = S.learning_methods(settings, learning)
    assert sorted(set(table["method"].to_list())) == sorted(learners)
    from prep.tensor import load

    tensor = load(learning_run / "results" / "data" / "milan")
    _, val = learning_days(tensor, learning.validation_days)
    want_days = ";".join(tensor.labels[d] for d in val)
    test_labels = {tensor.labels[int(d)] for d in tensor.test_days}
    assert want_days == "2013-11-08;2013-11-09;2013-11-10"
    for method in learners:
        rows = table.filter(pl.col("method") == method).sort("fraction")
        assert rows["fraction"].to_list() == [0.0, *learning.ladder], method  # the untrained point, then the ladder
        assert rows["untrained"].to_list() == [True] + [False] * len(learning.ladder), method
        assert set(rows["seed"].to_list()) == {learning.seed}
        transitions, steps = rows["transitions"].to_list(), rows["gradient_steps"].to_list()
        points = list(zip(transitions, steps))
        assert all(b[0] >= a[0] and b[1] >= a[1] and b != a for a, b in zip(points, points[1:])), (method, points)
        if method not in ("dswm", "tdmpc"):  # they train on pre-collected transitions before their first update
            assert all(b > a for a, b in zip(transitions, transitions[1:])), (method, transitions)
        else:  # ... so every later snapshot is a later gradient step
            assert all(b > a for a, b in zip(steps, steps[1:])), (method, steps)
        assert steps[0] == 0, method
        assert rows["probe_sr"].is_between(0.0, 1.0).all(), method
    assert set(table["days"].to_list()) == {want_days} and not set(want_days.split(";")) & test_labels
    for col in ("static_sr", "greedy_sr"):
        assert table[col].n_unique() == 1 and table[col].null_count() == 0
    static = pl.read_parquet(learning_run / "results" / "learning" / "milan" / "static" / "seed0" / "curve.parquet")
    assert static["label"].to_list() == want_days.split(";") and set(static["split"].to_list()) == {"validation"}
    assert table["static_sr"][0] == pytest.approx(float(static["sr_mean"].mean()))
    verdict = read_csv(csv.with_name("learning_verdict.csv"))
    assert sorted(verdict["method"].to_list()) == sorted(learners) and tuple(verdict.columns) == VERDICT_COLUMNS
    for r in verdict.iter_rows(named=True):  # its served-ratio gain is the curve's, cap against untrained
        rows = table.filter(pl.col("method") == r["method"]).sort("fraction")["probe_sr"]
        assert r["sr_gain"] == pytest.approx(rows[-1] - rows[0]) and r["untrained_sr"] == pytest.approx(rows[0])
    # the learning audit the target needs read every run and passed: each learner's curve on its validation days
    report = json.loads((learning_run / "results" / "audit" / "learning.json").read_text())
    (chk,) = [c for c in report["checks"] if c["id"] == "protocol.learning_days"]
    assert report["passed"] and report["scope"] == "learning"
    runs = chk["evidence"]["runs"]
    assert sorted(runs) == sorted(f"milan/{m}/seed0" for m in [*learners, *S.learning_references(settings, learning)])
    for method in learners:
        assert runs[f"milan/{method}/seed0"]["validation_days"] == want_days.split(";"), method
        assert runs[f"milan/{method}/seed0"]["snapshots_hashed"] == len(learning.ladder) + 1, method


@pytest.mark.integration
def test_the_tables_target_schedules_no_learning_job(learning_run):
    from smoke import snakemake

    proc = snakemake(learning_run, "tables", "-n", "--cores", "2")
    assert proc.returncode == 0, proc.stderr[-3000:]
    rules = set(re.findall(r"^(?:local)?rule (\w+):", proc.stdout + proc.stderr, flags=re.M))
    assert "train" in rules and not {r for r in rules if r.startswith("learning") or r.endswith("learning_curves")}
