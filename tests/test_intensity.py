"""The demand intensity u: a number in config.yaml, or `calibrate` (the calibrate rule's record, read by every job
that needs u); and the scenario's parse-time messages name the key, the allowed range and the value found."""
from __future__ import annotations

import copy
import dataclasses
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import ROOT
from dswm import settings as S
from dswm.config import ConfigError, load_yaml, to_plain
from dswm.pipeline import setup
from dswm.sim.scenario import CALIBRATE, DEMO_INTENSITY, Scenario

RECORD = "results/calibration/demand_intensity.json"
READERS = ("select", "train", "evaluate", "audit_report")
"""The rules whose jobs read u."""


@pytest.fixture
def config():
    return load_yaml(ROOT / "config.yaml")


def with_intensity(config: dict, value) -> dict:
    cfg = copy.deepcopy(config)
    cfg["scenario"]["demand_intensity"] = value
    return cfg


def refusal(config: dict) -> str:
    with pytest.raises(ConfigError) as err:
        S.resolve(config)
    return str(err.value)


# ---- parse time ------------------------------------------------------------------------------------------
def test_calibrate_is_the_default_and_a_number_stays_allowed(config):
    assert config["scenario"]["demand_intensity"] == CALIBRATE
    assert S.resolve(config).scenario.demand_intensity == CALIBRATE
    assert S.resolve(with_intensity(config, 65.58)).scenario.demand_intensity == 65.58


def test_an_obs_window_outside_the_day_is_refused_naming_obs_window(config):
    cfg = copy.deepcopy(config)
    cfg["scenario"]["obs_window"] = 500
    assert refusal(cfg) == ("invalid configuration:\nconfig.yaml: key 'scenario.obs_window' must be an integer in "
                            "[1, 143] (fewer than the 144 slots of a day, scenario.slots_per_day); found 500")
    cfg["scenario"]["obs_window"] = 0
    assert refusal(cfg).endswith("key 'scenario.obs_window' must be an integer in [1, 143] (fewer than the 144 "
                                 "slots of a day, scenario.slots_per_day); found 0")
    plain = {**config["scenario"], "demand_intensity": 65.58, "obs_window": 144}  # past the schema (a job's slice)
    with pytest.raises(ConfigError, match="^" + re.escape(
            "config key scenario.obs_window: expected an integer in [1, 143] (fewer than the 144 slots of "
            "scenario.slots_per_day), found 144") + "$"):
        Scenario.from_dict(plain)


@pytest.mark.parametrize("value", ["calibrat", 0, -65.58, True])
def test_a_demand_intensity_that_is_neither_a_positive_number_nor_calibrate_is_refused(config, value):
    assert refusal(with_intensity(config, value)) == (
        "invalid configuration:\nconfig.yaml: key 'scenario.demand_intensity' must be a positive number (u), or "
        "calibrate (u from the calibrate rule's record, results/calibration/demand_intensity.json); "
        f"found {value!r}")


def test_the_scenario_builder_refuses_a_bad_intensity_past_the_schema(config):
    for value, found in (("calibrat", "'calibrat'"), (0.0, "0.0"), (float("nan"), "nan")):
        with pytest.raises(ConfigError, match="^" + re.escape(
                f"config key scenario.demand_intensity: expected a positive number or 'calibrate', found {found}")):
            Scenario.from_dict({**config["scenario"], "demand_intensity": value})


# ---- which jobs depend on the calibrate rule --------------------------------------------------------------
def test_only_calibrate_makes_the_record_an_input(config):
    assert S.intensity_inputs(S.resolve(config)) == {"intensity": RECORD}
    assert S.intensity_inputs(S.resolve(with_intensity(config, 65.58))) == {}
    assert S.CALIBRATION_RECORD == RECORD


def test_the_calibrate_job_never_reads_u_and_every_reader_holds_the_choice_in_its_slice(config):
    cal, num = S.resolve(config), S.resolve(with_intensity(config, 65.58))
    assert "demand_intensity" not in S.calibrate_slice(cal)["scenario"]
    assert S.param(S.calibrate_slice(cal)) == S.param(S.calibrate_slice(num))
    for slices in ([S.train_slice(s, "dswm"), S.evaluate_slice(s, "greedy"), S.select_slice(s), S.audit_slice(s)]
                   for s in (cal, num)):
        assert [sl["scenario"]["demand_intensity"] for sl in slices] in ([CALIBRATE] * 4, [65.58] * 4)
    # switching between a number and `calibrate` changes every reader's slice, so Snakemake reruns it
    assert S.param(S.evaluate_slice(cal, "greedy")) != S.param(S.evaluate_slice(num, "greedy"))
    assert S.Settings.from_plain(S.audit_slice(cal)).scenario.demand_intensity == CALIBRATE


def dry_run(workdir: Path, config_text: str) -> str:
    (workdir / "config.yaml").write_text(config_text)
    out = subprocess.run([str(Path(sys.executable).parent / "snakemake"), "-n", "--forceall", "--nolock",
                          "--cores", "2", "tables", "select", "--snakefile", str(ROOT / "Snakefile"),
                          "--directory", str(workdir), "--config", "profile=smoke"],
                         cwd=workdir, capture_output=True, text=True, timeout=180)
    assert out.returncode == 0, out.stdout + out.stderr
    return out.stdout


def rule_inputs(text: str) -> dict[str, list[list[str]]]:
    """{rule: [inputs of each of its jobs]} of a dry run's job list."""
    found: dict[str, list[list[str]]] = {}
    for rule, inputs in re.findall(r"^rule (\w+):\n(?:\s+input: ([^\n]*)\n)?", text, flags=re.M):
        found.setdefault(rule, []).append(inputs.split(", ") if inputs else [])
    return found


def test_calibrate_puts_the_rule_upstream_of_every_job_that_reads_u_and_a_number_keeps_it_out(tmp_path):
    text = (ROOT / "config.yaml").read_text()
    calibrated = rule_inputs(dry_run(tmp_path, text))
    assert len(calibrated["calibrate"]) == 1
    for rule in READERS:
        assert calibrated[rule] and all(RECORD in inputs for inputs in calibrated[rule]), rule
    assert not any(RECORD in inputs for rule in ("prepare", "mlflow_init", "calibrate") for inputs in calibrated[rule])
    numbered, n = re.subn(r"(?m)^  demand_intensity: .*$", "  demand_intensity: 65.58", text)
    assert n == 1
    plain = rule_inputs(dry_run(tmp_path, numbered))
    assert "calibrate" not in plain
    assert not any(RECORD in inputs for jobs_of in plain.values() for inputs in jobs_of)
    assert {r: len(v) for r, v in plain.items()} == {r: len(v) for r, v in calibrated.items() if r != "calibrate"}


# ---- the record --------------------------------------------------------------------------------------------
def write_record(tmp_path: Path, content) -> Path:
    path = tmp_path / "demand_intensity.json"
    path.write_text(content if isinstance(content, str) else json.dumps(content))
    return path


@pytest.mark.parametrize("content, message", [
    ({"served_ratio": 0.74}, "{path}: missing key 'demand_intensity' (expected the positive u the calibrate rule "
                             "writes; run it again)"),
    ({"demand_intensity": 0.0}, "{path}: key 'demand_intensity' must be a positive number; found 0.0 (run the "
                                "calibrate rule again)"),
    ({"demand_intensity": -65.58}, "{path}: key 'demand_intensity' must be a positive number; found -65.58 (run the "
                                   "calibrate rule again)"),
    ({"demand_intensity": "65.58"}, "{path}: key 'demand_intensity' must be a positive number; found '65.58' (run "
                                    "the calibrate rule again)"),
    ([65.58], "{path}: missing key 'demand_intensity' (expected the positive u the calibrate rule writes; run it "
              "again)"),
])
def test_a_record_without_a_positive_intensity_is_refused_naming_the_file_and_key(tmp_path, content, message):
    path = write_record(tmp_path, content)
    with pytest.raises(ConfigError, match="^" + re.escape(message.format(path=path)) + "$"):
        S.read_intensity(path)


def test_a_missing_or_unreadable_record_is_refused_naming_the_file(tmp_path):
    missing = tmp_path / "demand_intensity.json"
    with pytest.raises(ConfigError, match="^" + re.escape(
            f"{missing}: no calibration record (scenario.demand_intensity is 'calibrate', so u is read from this "
            f"file; run the calibrate rule)") + "$"):
        S.read_intensity(missing)
    with pytest.raises(ConfigError, match="^" + re.escape(f"{missing}: not a calibration record (")):
        S.read_intensity(write_record(tmp_path, "{"))


def test_jobs_simulate_and_hash_the_number_of_the_record(config, tmp_path):
    record = write_record(tmp_path, {"demand_intensity": 70.25, "served_ratio": 0.74})
    cal = S.resolve(config)
    scenario = S.calibrated_scenario(cal.scenario, record)
    numbered = S.resolve(with_intensity(config, 70.25)).scenario
    assert scenario == numbered and scenario.hash() == numbered.hash() and scenario.intensity == 70.25
    with pytest.raises(ConfigError, match=re.escape("scenario.demand_intensity is 'calibrate': read u from")):
        cal.scenario.hash()  # an unresolved scenario has no hash to record
    with pytest.raises(ConfigError, match=re.escape(f"no calibration record was given (expected {RECORD}")):
        S.calibrated_scenario(cal.scenario, None)
    assert S.calibrated_scenario(numbered, tmp_path / "absent.json") is numbered  # a number reads no record
    # the jobs' own resolution, and what their MLflow run logs and hashes
    job = S.evaluate_slice(cal, "greedy")
    used = setup.set_up(job, "evaluation", S.EvaluationSettings, record)
    assert used.scenario == scenario
    assert used.job["scenario"] == to_plain(numbered)
    scaled = setup.set_up({**job, "intensity_scale": 2.0}, "evaluation", S.EvaluationSettings, record)  # a u variant
    assert scaled.scenario.intensity == 140.5 and scaled.job["scenario"]["demand_intensity"] == 140.5
    with pytest.raises(ConfigError, match="no calibration record was given"):
        setup.set_up(job, "evaluation", S.EvaluationSettings, None)


def test_the_standin_intensity_is_only_for_scenarios_without_a_record():
    from dswm.sim.env import default_scenario
    from dswm.sim.scenario import load_scenario

    assert load_scenario(ROOT / "config.yaml").demand_intensity == CALIBRATE
    assert default_scenario() == dataclasses.replace(load_scenario(ROOT / "config.yaml"),
                                                     demand_intensity=DEMO_INTENSITY)
