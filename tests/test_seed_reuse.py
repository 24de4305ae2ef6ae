"""Methods whose result the seed does not change are evaluated once per dataset: evaluation.reuse_seed_independent."""
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import polars as pl
import pytest

from dswm import settings as runconfig
from dswm.config import load_yaml
from dswm.methods.classical import GreedyController, StaticController
from dswm.methods.search import SearchSettings
from dswm.protocol.evaluation import evaluate, write_days, write_eval_record
from dswm.protocol.reuse import reuse_evaluation
from prep.atomic import save_npz
from test_evaluation import RUN, toy_tensor

from conftest import ROOT, dry_run_blocks

LIMITS = {"id": 1, "ood": 1}
TIMING = "plan_ms_per_slot"
"""The one column of a day that is a measurement of the machine, not of the method."""
MODEL_RECORD = {"method": "static", "train_source": None, "model": None, "model_sha256": None, "train_manifest": None}


@pytest.fixture(scope="module")
def smoke_settings():
    return runconfig.resolve({**load_yaml(ROOT / "config.yaml"), "profile": "smoke"})


def _method_record(ctl) -> dict:
    return {"method": ctl.name, "class": f"{type(ctl).__module__}:{type(ctl).__name__}", "options": None,
            "search": None}


def test_the_deterministic_methods_give_the_same_days_at_every_seed(smoke_settings, make_scenario):
    """Every method of `methods.run` whose class says the seed leaves its result unchanged, at the smoke profile's
    settings, on one ID and one OOD day: seeds 0 and 7 differ in the seed column and the planning time alone."""
    scenario = make_scenario(n_uavs=4)
    tensor = toy_tensor()
    deterministic = [m for m, spec in smoke_settings.methods.items() if spec.controller_class.deterministic]
    assert deterministic == ["greedy", "static", "oracle", "ceiling"]  # JTORATC's degradation rule reads the clock
    for m in deterministic:
        spec = smoke_settings.methods[m]
        days = [evaluate(tensor=tensor, controller=spec.controller_class(name=m, seed=seed, options=spec.options),
                         scenario=scenario, seed=seed, limits=LIMITS, profile="smoke", **RUN).days
                for seed in (0, 7)]
        assert days[0]["seed"].to_list() == [0, 0] and days[1]["seed"].to_list() == [7, 7]
        assert days[0].drop("seed", TIMING).equals(days[1].drop("seed", TIMING)), m


def test_only_the_later_seeds_of_a_deterministic_method_reuse_and_only_when_the_setting_says_so():
    config = load_yaml(ROOT / "config.yaml")
    s = runconfig.resolve(config)  # the demo: Milan seeds 0 and 1, Shanghai seed 0
    assert s.seeds("milan") == [0, 1] and s.evaluation.reuse_seed_independent
    got = {(m, seed): runconfig.reused_seed(s, "milan", m, seed) for m in ("ceiling", "static", "ppo", "dswm")
           for seed in (0, 1)}
    assert got == {("ceiling", 0): None, ("ceiling", 1): 0, ("static", 0): None, ("static", 1): 0,
                   ("ppo", 0): None, ("ppo", 1): None, ("dswm", 0): None, ("dswm", 1): None}
    off = runconfig.resolve({**config, "evaluation": {**config["evaluation"], "reuse_seed_independent": False}})
    assert runconfig.reused_seed(off, "milan", "ceiling", 1) is None
    bad = {**config, "evaluation": {**config["evaluation"], "reuse_seed_independent": "yes"}}
    with pytest.raises(runconfig.ConfigError, match="evaluation.reuse_seed_independent' must be true or false"):
        runconfig.validate_config(bad, runconfig.load_schema(runconfig.SCHEMA))


def _job_inputs(text: str) -> dict[str, list[str]]:
    """{rule and first output: input files} of every job block of a dry run."""
    found = {}
    for (rule, out), block in dry_run_blocks(text).items():
        inp = re.search(r"^\s+input: (.+)$", block, flags=re.M)
        found[f"{rule} {out}"] = inp.group(1).split(", ") if inp else []
    return found


def test_the_workflow_gives_a_later_seeds_job_the_first_seeds_evaluation_main_and_extra():
    """In the DAG (a smoke dry run with Milan seeds 0 and 1 in the profile and the figures): the evaluate and the
    extra_evaluate job of seed 1 of a deterministic method read seed 0's three files; a learning method's do not."""
    targets = [f"results/{sub}/{m}/seed1/days.parquet"
               for sub in ("milan", "extra/milan/u2") for m in ("static", "dswm")]
    proc = subprocess.run([str(Path(sys.executable).parent / "snakemake"), "-n", "--forceall", "--nolock",
                           "--cores", "2", *targets, "--config", "profile=smoke",
                           "profiles={smoke: {seeds: {milan: [0, 1]}}}", "figures={budgets: {smoke: {seeds: [0, 1]}}}"],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    jobs = _job_inputs(proc.stdout + proc.stderr)
    for rule, sub in (("evaluate", "milan"), ("extra_evaluate", "extra/milan/u2")):
        first = f"results/{sub}/static/seed0"
        assert {f"{first}/days.parquet", f"{first}/trajectory.npz", f"{first}/eval_manifest.json"} <= \
            set(jobs[f"{rule} results/{sub}/static/seed1/days.parquet"]), rule
        assert f"{rule} {first}/days.parquet" in jobs      # which the dry run schedules first
        assert not [f for f in jobs[f"{rule} results/{sub}/dswm/seed1/days.parquet"] if "seed0" in f], rule


def _source(tmp_path, tensor, scenario, ctl):
    """The seed-0 evaluation of ``ctl`` written as an evaluate job writes it."""
    res = evaluate(tensor=tensor, controller=ctl, scenario=scenario, seed=0, limits=LIMITS, profile="smoke", **RUN)
    src = {"days": tmp_path / "days.parquet", "trajectory": tmp_path / "trajectory.npz",
           "record": tmp_path / "eval_manifest.json"}
    write_days(res.days, src["days"], MODEL_RECORD, _method_record(ctl))
    save_npz(src["trajectory"], **res.trajectories)
    write_eval_record(src["record"], {"days.parquet": src["days"], "trajectory.npz": src["trajectory"]})
    return src, res


def test_a_reused_evaluation_is_the_one_the_seed_would_have_given(tmp_path, make_scenario):
    scenario, tensor = make_scenario(n_uavs=4), toy_tensor()
    ctl = GreedyController(name="greedy", options=SearchSettings(sweeps=1, lattice=5, refine=0, bw_logits=()))
    src, _ = _source(tmp_path, tensor, scenario, ctl)
    reused, model = reuse_evaluation(src, tensor=tensor, controller=ctl, scenario=scenario, seed=3, limits=LIMITS,
                                     profile="smoke", method_record=_method_record(ctl))
    fresh = evaluate(tensor=tensor, controller=ctl, scenario=scenario, seed=3, limits=LIMITS, profile="smoke", **RUN)
    assert model == MODEL_RECORD
    assert reused.days["seed"].to_list() == [3, 3] and reused.days["seed"].dtype == pl.Int32
    assert reused.days.drop(TIMING).equals(fresh.days.drop(TIMING))
    assert sorted(reused.trajectories) == sorted(fresh.trajectories)
    for k, v in fresh.trajectories.items():
        assert np.array_equal(reused.trajectories[k], v) and reused.trajectories[k].dtype == np.asarray(v).dtype, k


def test_a_source_that_is_not_this_jobs_evaluation_is_refused_with_the_file_and_what_differs(tmp_path, make_scenario):
    scenario, tensor = make_scenario(n_uavs=4), toy_tensor()
    ctl = StaticController(name="static")
    src, _ = _source(tmp_path, tensor, scenario, ctl)
    kw = dict(tensor=tensor, scenario=scenario, seed=1, profile="smoke", method_record=_method_record(ctl))

    with pytest.raises(ValueError, match=r"days.parquet: column eval_days_hash holds"):
        reuse_evaluation(src, controller=ctl, limits={"id": 2, "ood": 1}, **kw)  # other days
    with pytest.raises(ValueError, match=r"days.parquet: column scenario_hash holds"):
        reuse_evaluation(src, controller=ctl, limits=LIMITS,
                         **{**kw, "scenario": make_scenario(n_uavs=4, demand_intensity=2 * scenario.demand_intensity)})
    other = {**_method_record(ctl), "options": {"lattice": 9}}
    with pytest.raises(ValueError, match=r"days.parquet: its method record .* is not this job's"):
        reuse_evaluation(src, controller=ctl, limits=LIMITS, **{**kw, "method_record": other})
    class Drawn(StaticController):  # a class that does not say the seed leaves its result unchanged
        deterministic = False

    with pytest.raises(ValueError, match=r"static: its class \(Drawn\) does not say the seed leaves"):
        reuse_evaluation(src, controller=Drawn(name="static"), limits=LIMITS, **kw)
    src["trajectory"].write_bytes(src["trajectory"].read_bytes() + b"\0")  # changed after its record was written
    with pytest.raises(ValueError, match=r"trajectory.npz: its SHA-256 is not the one .*eval_manifest.json records"):
        reuse_evaluation(src, controller=ctl, limits=LIMITS, **kw)
