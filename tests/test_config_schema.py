"""Config validation and profile resolution: the repository's config passes; each bad input stops up front."""
import ast
import copy
import dataclasses
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from dswm import settings as runconfig
from dswm.config import ConfigError, load_yaml, with_budget
from dswm.methods import registry
from dswm.methods.tdmpc import settings as tdmpc_settings

from conftest import ROOT

SCHEMA = runconfig.load_schema(runconfig.SCHEMA)


@pytest.fixture
def config():
    return load_yaml(ROOT / "config.yaml")


def error_of(config):
    with pytest.raises(ConfigError) as err:
        runconfig.validate_config(config, SCHEMA)
    return str(err.value)


def test_the_repository_config_is_valid_and_every_level_refuses_unknown_keys(config):
    runconfig.validate_config(config, SCHEMA)

    objects = []

    def walk(node, where):
        if isinstance(node, dict):
            if node.get("type") == "object" or "properties" in node or "patternProperties" in node:
                objects.append((where, node.get("additionalProperties")))
            for key, sub in node.items():
                walk(sub, f"{where}/{key}")
        elif isinstance(node, list):
            for i, sub in enumerate(node):
                walk(sub, f"{where}[{i}]")
    walk(SCHEMA, "#")
    assert len(objects) > 40
    assert [w for w, extra in objects if extra is not False] == []


@pytest.mark.parametrize("mutate, words", [
    (lambda c: c["evaluation"].update(batch_dayz=True),
     ["unknown key 'evaluation.batch_dayz'", "did you mean 'batch_days'"]),
    (lambda c: c["scenario"]["channel"].update(eta_los=1.0), ["unknown key 'scenario.channel.eta_los'"]),
    (lambda c: c["datasets"]["milan"]["crop"].update(rows="twenty"), ["'datasets.milan.crop.rows'", "integer >= 1",
                                                                      "'twenty'"]),
    (lambda c: c["evaluation"].update(batch_days="yes"), ["'evaluation.batch_days'", "true or false"]),
    (lambda c: c["profiles"]["demo"]["seeds"].update(milan=[]), ["'profiles.demo.seeds.milan'", "non-empty list"]),
    (lambda c: c["mlflow"].pop("store"), ["missing key 'mlflow.store'", ".db"]),
    (lambda c: c["methods"]["user"].update(mine={"class": "just_a_name"}),
     ["'methods.user.mine.class'", "package.module:ClassName"]),
    (lambda c: c["datasets"]["shanghai"].update(source="real"), ["'datasets.shanghai.source'", "demo", "raw"]),
    (lambda c: c["dswm"]["budgets"]["smoke"].update(stepz=1), ["unknown key 'dswm.budgets.smoke.stepz'"]),
    (lambda c: c["scenario"].update(slots_per_day=96), ["'scenario.slots_per_day'", "144", "found 96"]),
    (lambda c: c["scenario"].update(reserve_frac=0), ["'scenario.reserve_frac'", "strictly between 0 and 1"]),
    (lambda c: c["search"].update(bw_logits=[-0.5, 0.5]), ["'search.bw_logits'", "includes 0", "[-0.5, 0.5]"]),
    (lambda c: c["search"].update(lattice=6), ["'search.lattice'", "odd integer", "found 6"]),
    (lambda c: c["dswm"]["planner"].update(sigma0_later=-0.1), ["'dswm.planner.sigma0_later'", "or null"]),
    (lambda c: c["dswm"]["planner"].pop("carry_best"), ["missing key 'dswm.planner.carry_best'"]),
    (lambda c: c["dswm"]["training"]["collect_search"].update(lattice=4),
     ["'dswm.training.collect_search.lattice'", "odd integer", "found 4"]),
    (lambda c: c["methods"]["tdmpc"]["precollect"].pop("transitions"),
     ["missing key 'methods.tdmpc.precollect.transitions'"]),
    (lambda c: c["methods"]["tdmpc"]["budgets"]["smoke"]["precollect"].update(transitions=0),
     ["'methods.tdmpc.budgets.smoke.precollect.transitions'", "integer >= 1"]),
])
def test_bad_keys_and_values_are_named_with_the_expected_form(config, mutate, words):
    bad = copy.deepcopy(config)
    mutate(bad)
    msg = error_of(bad)
    for w in words:
        assert w in msg, f"{w!r} not in: {msg}"


def test_resolution_keeps_only_the_selected_profile_and_its_hash_differs(config):
    demo = runconfig.resolve(config)
    assert demo.profile == "demo" and demo.run.datasets == tuple(config["profiles"]["demo"]["datasets"])
    assert demo.run.seeds == {d: tuple(s) for d, s in config["profiles"]["demo"]["seeds"].items()}
    smoke = runconfig.resolve({**config, "profile": "smoke"})
    assert (smoke.run.eval_days.id, smoke.run.eval_days.ood) == (1, 1)
    assert demo.hash() != smoke.hash()
    assert demo.hash() == runconfig.resolve(copy.deepcopy(config)).hash()
    jobs = demo.jobs()
    everywhere = [m for m in config["methods"]["run"] if m not in config["methods"]["only_on"]]
    assert len(jobs) == sum(len(demo.run.seeds[d]) * (len(everywhere) + sum(d in on for on in
                                                                            config["methods"]["only_on"].values()))
                            for d in demo.run.datasets)
    with pytest.raises(ConfigError, match="'profile' must be one of demo, smoke, paper; found 'fast'"):
        runconfig.resolve({**config, "profile": "fast"})


def test_settings_are_typed_and_come_back_from_their_plain_form(config):
    s = runconfig.resolve(config)
    assert s.methods["greedy"].options.sweeps == config["search"]["sweeps"]
    assert s.methods["dswm_plus"].options.planner.search == s.methods["oracle"].options  # the one search
    assert s.methods["dswm"].options.planner.n_samples == config["dswm"]["budgets"]["demo"]["planner"]["n_samples"]
    assert s.methods["dswm_wo_unc"].options.planner.lambda_u == 0.0
    assert s.display.progress_mininterval_s == config["evaluation"]["progress_mininterval_s"]
    back = runconfig.Settings.from_plain(runconfig.audit_slice(s))
    # the audit reads no figure setting, no scheduler request and no tracking setting
    assert back == dataclasses.replace(s, display=None, selection=None, figures=None, resources=None, mlflow=None)
    sel = runconfig.select_slice(s)["selection"]
    assert runconfig.build(runconfig.SelectionSettings, sel, "selection") == s.selection


def test_a_slice_is_the_same_text_whatever_the_key_order_of_the_yaml(config):
    def reordered(node):
        return {k: reordered(node[k]) for k in reversed(list(node))} if isinstance(node, dict) else node

    a, b = runconfig.resolve(config), runconfig.resolve(reordered(config))
    for method in config["methods"]["run"]:
        assert runconfig.param(runconfig.evaluate_slice(a, method)) == runconfig.param(runconfig.evaluate_slice(b, method))
    assert runconfig.param(runconfig.audit_slice(a)) == runconfig.param(runconfig.audit_slice(b))
    changed = copy.deepcopy(config)
    changed["evaluation"]["progress_mininterval_s"] = 30.0
    c = runconfig.resolve(changed)
    assert runconfig.param(runconfig.evaluate_slice(c, "greedy")) == runconfig.param(runconfig.evaluate_slice(a, "greedy"))
    changed["scenario"]["altitude_m"] = 120.0
    d = runconfig.resolve(changed)
    assert runconfig.param(runconfig.evaluate_slice(d, "greedy")) != runconfig.param(runconfig.evaluate_slice(a, "greedy"))
    assert runconfig.param(runconfig.prep_slice(d, "milan")) == runconfig.param(runconfig.prep_slice(a, "milan"))


def test_a_train_slice_holds_no_planner_setting(config):
    a = runconfig.resolve(config)
    changed = copy.deepcopy(config)
    changed["dswm"]["planner"]["gamma"] = 0.9
    b = runconfig.resolve(changed)
    assert runconfig.param(runconfig.train_slice(a, "dswm")) == runconfig.param(runconfig.train_slice(b, "dswm"))
    assert runconfig.param(runconfig.evaluate_slice(a, "dswm")) != runconfig.param(runconfig.evaluate_slice(b, "dswm"))
    assert runconfig.train_slice(a, "dswm")["method"]["options"]["planner"] is None


def test_a_profile_dataset_without_seeds_is_refused(config):
    cfg = copy.deepcopy(config)
    del cfg["profiles"]["demo"]["seeds"]["yjmob"]
    with pytest.raises(ConfigError, match=r"profiles\.demo\.seeds\.yjmob' is missing"):
        runconfig.resolve(cfg)


def test_raw_source_without_its_files_is_refused(config, tmp_path):
    cfg = copy.deepcopy(config)
    cfg["datasets"]["yjmob"]["source"] = "raw"
    cfg["datasets"]["yjmob"]["raw_files"] = ["data/raw/yjmob/yjmob100k-dataset1.csv.gz"]
    with pytest.raises(ConfigError) as err:
        runconfig.resolve(cfg, root=tmp_path)
    assert "datasets.yjmob.raw_files[0]" in str(err.value) and "source: demo" in str(err.value)
    (tmp_path / "data" / "raw" / "yjmob").mkdir(parents=True)
    (tmp_path / "data" / "raw" / "yjmob" / "yjmob100k-dataset1.csv.gz").write_bytes(b"")
    runconfig.resolve(cfg, root=tmp_path)  # present now: accepted
    cfg["datasets"]["milan"]["source"] = "raw"  # a glob that matches nothing
    with pytest.raises(ConfigError, match=r"datasets\.milan\.raw_files\[0\]"):
        runconfig.resolve(cfg, root=tmp_path)


@pytest.mark.parametrize("mutate, words", [
    (lambda c: c["profiles"]["demo"]["seeds"].update(shanghai=[]),       # the schema
     ["profiles.demo.seeds.shanghai", "non-empty list"]),
    (lambda c: c["scenario"].update(obs_window=500),                    # the observation window within a day
     ["key 'scenario.obs_window' must be an integer in [1, 143]", "found 500"]),
    (lambda c: c["dswm"]["budgets"]["demo"]["planner"].update(n_samples=64, n_elites=65),  # the merged planner
     ["method 'dswm'", "dswm.planner.n_elites", "dswm.budgets.demo.planner", "n_elites=65, n_samples=64"]),
    (lambda c: (c["profiles"]["demo"].update(datasets=["milan", "yjmob"]),   # Table III of a dataset not run
                c["tables"].update(main_dataset="shanghai")),
     ["'tables.main_dataset' is 'shanghai'", "profiles.demo.datasets: milan, yjmob"]),
])
def test_snakemake_stops_before_any_job_on_a_bad_config(config, tmp_path, mutate, words):
    bad = copy.deepcopy(config)
    mutate(bad)
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump(bad))
    snakemake = os.path.join(os.path.dirname(sys.executable), "snakemake")
    proc = subprocess.run([snakemake, "tables", "-n", "--cores", "1", "--configfile", str(tmp_path / "bad.yaml")],
                          cwd=ROOT, capture_output=True, text=True, timeout=300)
    out = proc.stdout + proc.stderr
    assert proc.returncode != 0
    for w in words:
        assert w in out, f"{w!r} not in: {out[-2000:]}"
    assert "Job stats" not in out  # nothing was scheduled


def test_only_on_keeps_a_method_to_its_datasets_and_its_mistakes_are_named(config):
    cfg = copy.deepcopy(config)
    cfg["methods"]["only_on"] = {"greedy": ["milan", "yjmob"]}
    s = runconfig.resolve(cfg)
    assert s.methods_on("shanghai") == [m for m in cfg["methods"]["run"] if m != "greedy"]
    assert s.methods_on("yjmob") == list(cfg["methods"]["run"])
    assert sorted(d for d, m, _ in s.jobs() if m == "greedy") == ["milan", "milan", "yjmob"]  # Milan: 2 seeds
    assert [(d, m) for d, m, _ in s.jobs() if m == "static"] == [("milan", "static")] * 2 + \
        [("shanghai", "static"), ("yjmob", "static")]
    assert runconfig.Settings.from_plain(runconfig.audit_slice(s)).methods_on("shanghai") == s.methods_on("shanghai")
    cfg["methods"]["only_on"] = {"gredy": ["milan"]}
    with pytest.raises(ConfigError, match="'methods.only_on.gredy' names 'gredy', which is not a registered method"):
        runconfig.resolve(cfg)
    cfg["methods"]["only_on"] = {"jtoratc": ["milan"]}  # a method left out of `run` keeps its entry, unused
    cfg["methods"]["run"] = ["static", "greedy"]
    assert runconfig.resolve(cfg).methods_on("shanghai") == ["static", "greedy"]
    cfg["methods"]["run"] = config["methods"]["run"]
    cfg["methods"]["only_on"] = {"greedy": ["shanghai"]}
    cfg["profiles"]["demo"]["datasets"] = ["milan"]
    with pytest.raises(ConfigError, match=r"'methods.only_on.greedy' is \['shanghai'\], none of which profile "
                                          r"'demo' runs \(profiles.demo.datasets: milan\)"):
        runconfig.resolve(cfg)
    cfg["methods"]["only_on"] = {"greedy": ["rome"]}
    with pytest.raises(ConfigError, match="methods.only_on.greedy"):
        runconfig.resolve(cfg)


# ---- where a value came from: config.yaml, a --configfile, --config (Snakemake's own parsing of it) -------------
def with_cli(config, *entries, files=()):
    """``config`` with the --configfile ``files`` ((name, data)) and the --config ``entries`` applied as Snakemake
    applies them (snakemake.cli.parse_config: a value nested in a mapping arrives as a string), and their sources."""
    from snakemake.cli import parse_config
    from snakemake.utils import update_config

    from dswm.config import ConfigSources

    merged = copy.deepcopy(config)
    for _, data in files:
        update_config(merged, copy.deepcopy(data))
    cli = parse_config(list(entries))
    update_config(merged, copy.deepcopy(cli))
    return merged, ConfigSources(layers=(*files, (ConfigSources.CLI, cli)))


def test_a_nested_config_value_arrives_as_a_string_and_is_read_where_the_schema_wants_a_number(config):
    merged, sources = with_cli(config, 'scenario={"n_uavs": 3}', 'evaluation={"batch_days": false}',
                               'profiles={"demo": {"seeds": {"milan": [4, 5]}}}')
    assert merged["scenario"]["n_uavs"] == "3" and merged["evaluation"]["batch_days"] == "false"  # Snakemake's
    s = runconfig.resolve(merged, sources=sources)
    assert s.scenario.n_uavs == 3 and s.evaluation.batch_days is False and s.seeds("milan") == [4, 5]
    assert s.methods["greedy"].options.sweeps == config["search"]["sweeps"]  # the rest as config.yaml says


def test_a_nested_config_string_the_schema_cannot_read_says_it_came_from_config_as_a_string(config):
    merged, sources = with_cli(config, 'scenario={"n_uavs": "three"}')
    with pytest.raises(ConfigError) as err:
        runconfig.resolve(merged, sources=sources)
    assert str(err.value) == (
        "invalid configuration:\n--config: key 'scenario.n_uavs' must be an integer >= 1; found 'three' (--config "
        "passed it as the string 'three': Snakemake reads a value nested in --config as a string, taken here as a "
        "number, boolean or null only where the schema expects one)")
    merged, sources = with_cli(config, 'scenario={"n_uavs": 0}')  # read as a number, then refused as one
    with pytest.raises(ConfigError) as err:
        runconfig.resolve(merged, sources=sources)
    assert str(err.value) == "invalid configuration:\n--config: key 'scenario.n_uavs' must be an integer >= 1; found 0"


def test_each_message_names_the_file_or_the_option_its_value_came_from(config):
    user = ("my/user.yaml", {"methods": {"run": ["static", "gredy"]}, "scenario": {"n_uavs": 0}})
    merged, sources = with_cli(config, 'methods={"run": []}', files=[user])
    with pytest.raises(ConfigError) as err:
        runconfig.resolve(merged, sources=sources)
    assert str(err.value) == (
        "invalid configuration:\n--config: key 'methods.run' must be a non-empty list of registered method names, "
        "e.g. [static, greedy, oracle]; found []\nmy/user.yaml: key 'scenario.n_uavs' must be an integer >= 1; "
        "found 0")
    merged, sources = with_cli(config, "profile=demo", files=[user[:1] + ({"methods": user[1]["methods"]},)])
    with pytest.raises(ConfigError) as err:  # a cross-key check after the schema
        runconfig.resolve(merged, sources=sources)
    assert str(err.value).startswith("my/user.yaml: key 'methods.run' names 'gredy', which is not a registered "
                                     "method")
    merged, sources = with_cli(config, "profile=nosuch")
    with pytest.raises(ConfigError) as err:
        runconfig.resolve(merged, sources=sources)
    assert str(err.value) == ("--config: key 'profile' must be one of demo, smoke, paper; found 'nosuch' (select one "
                              "with --config profile=NAME)")
    with pytest.raises(ConfigError) as err:  # nothing given: config.yaml
        runconfig.resolve({**config, "scenario": {**config["scenario"], "n_uavs": 0}})
    assert str(err.value) == "invalid configuration:\nconfig.yaml: key 'scenario.n_uavs' must be an integer >= 1; found 0"


BELONG = ("refused; a tracking server's credentials belong in the environment (MLFLOW_TRACKING_USERNAME, "
          "MLFLOW_TRACKING_PASSWORD) or in MLflow's credentials file ~/.mlflow/credentials, never in the config, whose "
          "values reach the jobs' params and, through --config, the command line that `ps` shows (docs/CLUSTER.md)")


@pytest.mark.parametrize("mutate, line", [
    (lambda c: c["mlflow"].update(tracking_uri="http://alice:s3cr3t-pw@trackhost:5000"),
     "config.yaml: key 'mlflow.tracking_uri' holds a URL with a user or password before its host "
     "(scheme://user:password@host): " + BELONG),
    (lambda c: c["mlflow"].update(tracking_uri="http://alice@trackhost:5000"),
     "config.yaml: key 'mlflow.tracking_uri' holds a URL with a user or password before its host "
     "(scheme://user:password@host): " + BELONG),
    (lambda c: c["mlflow"].update(password="s3cr3t-pw"),
     "config.yaml: key 'mlflow.password' is named like a credential ('password'): " + BELONG),
    (lambda c: c["mlflow"]["http"].update(api_token="s3cr3t-pw"),
     "config.yaml: key 'mlflow.http.api_token' is named like a credential ('api_token'): " + BELONG),
    (lambda c: c.update(tracking={"username": "alice", "db_password": "s3cr3t-pw"}),
     "config.yaml: key 'tracking.db_password' is named like a credential ('db_password'): " + BELONG),
])
def test_a_credential_in_the_config_is_refused_naming_the_key_never_its_value(config, mutate, line):
    bad = copy.deepcopy(config)
    mutate(bad)
    msg = error_of(bad)
    assert line in msg.splitlines() and "s3cr3t" not in msg and "alice" not in msg
    if "tracking" not in bad:  # the credential's key is the only violation: its other lines are left out
        assert msg == "invalid configuration:\n" + line


def test_a_credential_passed_with_config_is_refused_naming_config_never_its_value(config):
    merged, sources = with_cli(config, "mlflow={tracking_uri: 'http://alice:s3cr3t-pw@trackhost:5000'}")
    with pytest.raises(ConfigError) as err:
        runconfig.resolve(merged, sources=sources)
    assert str(err.value) == ("invalid configuration:\n--config: key 'mlflow.tracking_uri' holds a URL with a user or "
                              "password before its host (scheme://user:password@host): " + BELONG)
    merged, sources = with_cli(config, "mlflow={tracking_uri: 'http//alice:s3cr3t-pw@trackhost'}")  # malformed too
    with pytest.raises(ConfigError) as err:
        runconfig.resolve(merged, sources=sources)
    assert "s3cr3t" not in str(err.value) and "'mlflow.tracking_uri'" in str(err.value)


def test_snakemake_names_the_source_and_reads_nested_config_values(tmp_path):
    snakemake = os.path.join(os.path.dirname(sys.executable), "snakemake")

    def dry(*args):
        proc = subprocess.run([snakemake, "tables", "-n", "--nolock", "--cores", "1", *args], cwd=ROOT,
                              capture_output=True, text=True, timeout=300)
        return proc.returncode, proc.stdout + proc.stderr

    rc, out = dry("--config", 'scenario={"n_uavs":3}')  # valid: K = 3
    assert rc == 0, out[-3000:]
    (tmp_path / "user.yaml").write_text("scenario:\n  n_uavs: 0\n")
    rc, out = dry("--configfile", str(tmp_path / "user.yaml"), "--config", 'methods={"run": []}')
    assert rc != 0
    assert "--config: key 'methods.run' must be a non-empty list of registered method names" in out
    assert f"{tmp_path / 'user.yaml'}: key 'scenario.n_uavs' must be an integer >= 1; found 0" in out


def test_one_budget_merge_sets_a_nested_key_alone_and_names_the_entry():
    section = {"a": 1, "nested": {"x": 1, "y": 2}, "budgets": {"demo": {"nested": {"y": 5}}, "paper": None}}
    assert with_budget(section, "demo", "figures") == ({"a": 1, "nested": {"x": 1, "y": 5}},
                                                       "figures (with figures.budgets.demo)")
    assert with_budget(section, "smoke", "figures") == ({"a": 1, "nested": {"x": 1, "y": 2}}, "figures")
    assert with_budget({"a": 1, "budgets": None}, "demo", "resources") == ({"a": 1}, "resources")
    assert section["budgets"]["demo"] == {"nested": {"y": 5}} and section["nested"]["y"] == 2  # nothing changed
    with pytest.raises(ConfigError) as err:
        with_budget({"a": 1, "budgets": {"paper": {}}}, "demo", "dswm", required=True)
    assert str(err.value) == "config.yaml: key 'dswm.budgets' has no entry 'demo' (found ['paper'])"


def test_every_section_with_budgets_is_merged_the_same_way(config):
    """figures, resources, a method's section, TD-MPC's and DSWM's: the profile's entry over the section, one nested
    key alone, and a mistake inside a budget named with the entry it came from."""
    demo = runconfig.resolve(config)
    assert demo.figures.seeds == (0,) and demo.figures.do_probe.scales == (0.5, 2.0)  # the rest from `figures`
    smoke = runconfig.resolve({**config, "profile": "smoke"})
    assert (smoke.resources.of("train").runtime, smoke.resources.of("train").mem_mb) == (15, 4000)
    tdmpc = demo.methods["tdmpc"].options
    assert (tdmpc.steps, tdmpc.precollect.transitions, tdmpc.precollect.collect_parallel) == (800, 2860, 10)
    assert (tdmpc.gamma, smoke.methods["tdmpc"].options.steps) == (0.95, 40)
    dswm = demo.methods["dswm"].options
    assert (dswm.transitions, dswm.steps, dswm.planner.n_samples, dswm.planner.n_elites) == (2860, 400, 48, 6)
    # past the schema (a job's own builder): the key names the budget entry the value came from
    bad = copy.deepcopy(config)
    bad["methods"]["tdmpc"]["budgets"]["demo"]["steps"] = "many"
    bad["methods"]["sac"]["budgets"]["demo"]["batch_size"] = "x"
    bad["figures"]["budgets"]["demo"]["seeds"] = "x"
    with pytest.raises(ConfigError) as err:
        tdmpc_settings.resolve(bad, profile="demo")
    assert str(err.value) == ("config key methods.tdmpc (with methods.tdmpc.budgets.demo).steps: expected an "
                              "integer, found 'many'")
    with pytest.raises(ConfigError) as err:
        registry.lookup("sac", bad["methods"])[1].options_from_config(name="sac", config=bad, profile="demo")
    assert str(err.value) == ("config key methods.sac (with methods.sac.budgets.demo).batch_size: expected an "
                              "integer, found 'x'")
    with pytest.raises(ConfigError) as err:
        runconfig.figures_settings(bad, "demo")
    assert str(err.value) == "config key figures (with figures.budgets.demo).seeds: expected a list, found 'x'"


def undocumented_fields(package: Path) -> list[str]:
    """``file:line Class.field`` of every annotated class field in ``package`` without an attribute docstring."""
    bad = []
    for path in sorted(package.glob("*.py")):
        for cls in ast.walk(ast.parse(path.read_text())):
            if not isinstance(cls, ast.ClassDef):
                continue
            for field, after in zip(cls.body, [*cls.body[1:], None]):
                documented = (isinstance(after, ast.Expr) and isinstance(after.value, ast.Constant)
                              and isinstance(after.value.value, str))
                if isinstance(field, ast.AnnAssign) and isinstance(field.target, ast.Name) and not documented:
                    bad.append(f"{path.name}:{field.lineno} {cls.name}.{field.target.id}")
    return bad


def test_every_field_of_the_settings_package_has_a_docstring(tmp_path):
    assert undocumented_fields(ROOT / "src" / "dswm" / "settings") == []
    (tmp_path / "s.py").write_text('class A:\n    x: int\n    """Documented."""\n    y: int\n    z: int = 0\n')
    assert undocumented_fields(tmp_path) == ["s.py:4 A.y", "s.py:5 A.z"]
