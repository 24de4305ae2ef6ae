"""Controller interface and the method registry: built-in names, user classes by path, refusals."""
import copy
import sys
import textwrap

import numpy as np
import pytest

from dswm import controllers
from dswm.baselines import GreedyController, OracleController, StaticController
from dswm.config import ConfigError
from dswm.config import load_config
from dswm.runconfig import resolve

from conftest import ROOT

LEARNERS = ["dswm", "dswm_wo_unc", "dswm_wo_dec"]


@pytest.fixture(scope="module")
def resolved():
    return resolve(load_config(ROOT / "config.yaml"))


@pytest.fixture
def user_module(tmp_path, monkeypatch):
    """An importable module `my_methods` holding a user controller and a class that is not one."""
    (tmp_path / "my_methods.py").write_text(textwrap.dedent('''
        import numpy as np
        from dswm.controllers import Controller

        class Hover(Controller):
            label = "Hover (user)"
            table_class = "deployment"

            def __init__(self, *, name, seed=0, device="cpu", bw=0.0):
                super().__init__(name=name, seed=seed, device=device)
                self.bw = bw

            def reset(self, ctx):
                self.k = ctx.scenario.n_uavs

            def act(self, obs):
                a = np.zeros((self.k, 3), dtype=np.float32)
                a[:, 2] = self.bw
                return a

        class Fitter(Controller):
            """Learns; declares no training identity, so it always trains alone."""
            learns = True

            def __init__(self, *, name, seed=0, device="cpu", steps=1, greed=0.0):
                super().__init__(name=name, seed=seed, device=device)
                self.steps, self.greed = steps, greed

        class SharedFitter(Fitter):
            """Opts in: only `steps` shapes its training (`greed` acts at decision time)."""

            @classmethod
            def training_identity(cls, *, name, config):
                return str(config["methods"]["user"][name]["options"].get("steps", 1))

        class NotAController:
            pass
    '''))
    monkeypatch.syspath_prepend(str(tmp_path))
    yield "my_methods"
    sys.modules.pop("my_methods", None)


def test_builtin_methods_resolve_to_their_classes(resolved):
    assert controllers.controller_class("static", resolved) is StaticController
    assert controllers.controller_class("greedy", resolved) is GreedyController
    assert controllers.controller_class("oracle", resolved) is OracleController
    assert controllers.spec("greedy", resolved).table_class == "model-free"
    assert controllers.spec("static", resolved).label == "Static (K-means)"


def test_build_passes_the_method_section_as_keyword_arguments(resolved):
    g = controllers.build("greedy", config=resolved, seed=3)
    assert (g.name, g.seed, g.sweeps, g.lattice) == ("greedy", 3, resolved["methods"]["greedy"]["sweeps"],
                                                     resolved["methods"]["greedy"]["lattice"])
    o = controllers.build("oracle", config=resolved, seed=0)
    assert o.clairvoyant and not g.clairvoyant
    assert o.bw_logits[0] == 0.0 and sorted(o.bw_logits) == sorted(resolved["methods"]["oracle"]["bw_logits"])


def test_only_the_oracle_is_clairvoyant_and_only_dswm_variants_learn(resolved):
    classes = controllers.check_methods(resolved)
    assert [n for n, c in classes.items() if c.clairvoyant] == ["oracle"]
    assert sorted(n for n, c in classes.items() if c.learns) == ["dswm", "dswm_wo_dec", "dswm_wo_unc"]


def test_unregistered_method_names_the_key_and_the_expected_form(resolved):
    cfg = {**resolved, "methods": {**resolved["methods"], "run": ["static", "gredy"]}}
    with pytest.raises(ConfigError) as err:
        controllers.check_methods(cfg)
    msg = str(err.value)
    assert "methods.run" in msg and "'gredy'" in msg and "greedy" in msg and "package.module:ClassName" in msg


def test_user_method_by_class_path_with_options(resolved, user_module):
    methods = {**resolved["methods"], "run": ["static", "hover"],
               "user": {"hover": {"class": f"{user_module}:Hover", "options": {"bw": 0.5}}}}
    cfg = {**resolved, "methods": methods}
    assert list(controllers.check_methods(cfg)) == ["static", "hover"]
    spec = controllers.spec("hover", cfg)
    assert (spec.label, spec.table_class) == ("Hover (user)", "deployment")
    ctrl = controllers.build("hover", config=cfg, seed=1)
    assert ctrl.bw == 0.5 and ctrl.seed == 1


def test_user_class_that_is_not_a_controller_or_not_importable_is_refused(resolved, user_module):
    for target, words in [(f"{user_module}:NotAController", "not a subclass"),
                          ("no_such_module_xyz:Thing", "cannot import module")]:
        cfg = {**resolved, "methods": {**resolved["methods"], "run": ["x"], "user": {"x": {"class": target}}}}
        with pytest.raises(ConfigError) as err:
            controllers.check_methods(cfg)
        assert words in str(err.value) and "methods.user.x.class" in str(err.value)


def test_base_controller_refuses_what_it_does_not_implement():
    c = controllers.Controller(name="bare")
    with pytest.raises(NotImplementedError, match="does not learn"):
        c.fit(None, budget={}, run_dir=".")
    with pytest.raises(NotImplementedError, match="not batched"):
        c.act_batch({"fleet": np.zeros((1, 16, 7))})
    assert controllers.Controller.budget_from_config(name="bare", config={}) == {}


@pytest.mark.parametrize("profile", ["demo", "smoke", "paper"])
def test_dswm_wo_unc_shares_the_training_of_dswm_and_dswm_wo_dec_trains_alone(resolved, profile):
    cfg = {**resolved, "profile": profile}
    assert resolved["methods"]["run"][:3] == LEARNERS
    assert controllers.training_sources(cfg) == {"dswm": "dswm", "dswm_wo_unc": "dswm", "dswm_wo_dec": "dswm_wo_dec"}
    ident = {m: controllers.controller_class(m, cfg).training_identity(name=m, config=cfg) for m in LEARNERS}
    assert ident["dswm"] == ident["dswm_wo_unc"] != ident["dswm_wo_dec"]


@pytest.mark.parametrize("section, override", [("world_model", {"deter": 64}), ("training", {"lr": 3.0e-4})])
def test_a_method_that_overrides_what_shapes_training_trains_alone(resolved, section, override):
    cfg = copy.deepcopy(resolved)
    cfg["dswm"]["methods"]["dswm_wo_unc"][section] = override
    assert controllers.training_sources(cfg) == {m: m for m in LEARNERS}


def test_sharing_follows_the_settings_not_the_names(resolved):
    cfg = copy.deepcopy(resolved)
    cfg["dswm"]["methods"]["dswm_wo_unc"]["world_model"] = {"service_head": "mlp"}  # dswm_wo_dec's world model
    assert controllers.training_sources(cfg) == {"dswm": "dswm", "dswm_wo_unc": "dswm_wo_unc",
                                                 "dswm_wo_dec": "dswm_wo_unc"}


def test_planner_and_evaluation_settings_do_not_rerun_training_but_world_model_settings_do(resolved):
    base = controllers.training_rerun_params(resolved, "dswm")
    cfg = copy.deepcopy(resolved)
    cfg["dswm"]["planner"]["lambda_u"] = 0.5
    cfg["dswm"]["methods"]["dswm_wo_unc"]["planner"] = {"lambda_u": 0.25}
    cfg["evaluation"]["batch_days"] = not cfg["evaluation"]["batch_days"]
    assert controllers.training_rerun_params(cfg, "dswm") == base
    cfg["dswm"]["world_model"]["deter"] = 64
    assert controllers.training_rerun_params(cfg, "dswm")["training"] != base["training"]
    cfg = copy.deepcopy(resolved)
    cfg["scenario"]["n_uavs"] = 12
    assert controllers.training_rerun_params(cfg, "dswm")["scenario"]["n_uavs"] == 12


def test_the_first_method_in_run_order_is_the_training_source(resolved):
    cfg = copy.deepcopy(resolved)
    cfg["methods"]["run"] = ["static", "dswm_wo_unc", "dswm_wo_dec", "dswm"]
    assert controllers.training_sources(cfg) == {"dswm_wo_unc": "dswm_wo_unc", "dswm_wo_dec": "dswm_wo_dec",
                                                 "dswm": "dswm_wo_unc"}
    cfg["dswm"]["planner"]["lambda_u"] = 0.5  # planning settings never split a training
    cfg["dswm"]["budgets"]["demo"]["planner"] = {"n_samples": 8, "n_elites": 2}
    assert controllers.training_sources(cfg)["dswm"] == "dswm_wo_unc"


def test_user_learners_train_alone_unless_they_declare_a_training_identity(resolved, user_module):
    user = {"f1": {"class": f"{user_module}:Fitter", "options": {"greed": 0.1}},
            "f2": {"class": f"{user_module}:Fitter", "options": {"greed": 0.2}},
            "s1": {"class": f"{user_module}:SharedFitter", "options": {"steps": 5, "greed": 0.1}},
            "s2": {"class": f"{user_module}:SharedFitter", "options": {"steps": 5, "greed": 0.2}},
            "s3": {"class": f"{user_module}:SharedFitter", "options": {"steps": 9}}}
    cfg = {**resolved, "methods": {**resolved["methods"], "run": ["static", *user], "user": user}}
    assert controllers.training_sources(cfg) == {"f1": "f1", "f2": "f2", "s1": "s1", "s2": "s1", "s3": "s3"}
    assert controllers.Controller.training_identity(name="bare", config=cfg) is None
