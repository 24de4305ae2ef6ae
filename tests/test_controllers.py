"""Controller interface and the method registry: built-in names, user classes by path, typed settings, refusals."""
import copy
import sys
import textwrap

import numpy as np
import pytest

from dswm import settings as S
from dswm.config import ConfigError, load_yaml
from dswm.methods import registry
from dswm.methods.base import Controller
from dswm.methods.classical import GreedyController, OracleController, StaticController

from conftest import LEARNING_BASELINES, ROOT

LEARNERS = ["dswm", "dswm_wo_unc", "dswm_wo_dec"]


@pytest.fixture(scope="module")
def raw():
    return load_yaml(ROOT / "config.yaml")


@pytest.fixture(scope="module")
def settings(raw):
    return S.resolve(raw)


def sources(config):
    """The training sources of the learning methods but the baselines, DSWM+ left out (it shares dswm's in every case here); the
    learning baselines (ppo, sac, ...) are their own training sources (test below)."""
    return {m: src for m, src in S.resolve(config).training_sources().items()
            if m != "dswm_plus" and m not in LEARNING_BASELINES}


@pytest.fixture
def user_module(tmp_path, monkeypatch):
    """An importable module `my_methods` holding user controllers and a class that is not one."""
    (tmp_path / "my_methods.py").write_text(textwrap.dedent('''
        import dataclasses
        import numpy as np
        from dswm.methods.base import Controller

        @dataclasses.dataclass(frozen=True, kw_only=True)
        class HoverOptions:
            bw: float

        class Hover(Controller):
            label = "Hover (user)"
            table_class = "deployment"
            options_type = HoverOptions

            def reset(self, ctx):
                self.k = ctx.scenario.n_uavs

            def act(self, obs):
                a = np.zeros((self.k, 3), dtype=np.float32)
                a[:, 2] = self.options.bw
                return a

        @dataclasses.dataclass(frozen=True, kw_only=True)
        class FitOptions:
            steps: int
            greed: float

        class Fitter(Controller):
            """Learns; does not share training, so it always trains alone."""
            learns = True
            options_type = FitOptions

        @dataclasses.dataclass(frozen=True, kw_only=True)
        class FitTraining:
            steps: int

        class SharedFitter(Fitter):
            """Opts in: only `steps` shapes its training (`greed` acts at decision time)."""
            shares_training = True

            @classmethod
            def training_settings(cls, options):
                return FitTraining(steps=options.steps)

        class NotAController:
            pass
    '''))
    monkeypatch.syspath_prepend(str(tmp_path))
    yield "my_methods"
    sys.modules.pop("my_methods", None)


def with_user(raw, user, run):
    cfg = copy.deepcopy(raw)
    cfg["methods"]["user"] = user
    cfg["methods"]["run"] = run
    return cfg


def test_builtin_methods_resolve_to_their_classes(settings):
    assert settings.methods["static"].controller_class is StaticController
    assert settings.methods["greedy"].controller_class is GreedyController
    assert settings.methods["oracle"].controller_class is OracleController
    assert settings.methods["greedy"].table_class == "model-free"
    assert settings.methods["static"].label == "Static (K-means)"


def test_build_passes_the_typed_method_section(raw, settings):
    m = settings.methods["greedy"]
    g = registry.build("greedy", target=m.target, options=m.options, seed=3, device="cpu")
    want = raw["search"]
    assert (g.name, g.seed, g.search.sweeps, g.search.lattice, g.search.bw_logits) == \
        ("greedy", 3, want["sweeps"], want["lattice"], tuple(sorted(want["bw_logits"], key=abs)))
    o = settings.methods["oracle"]
    o = registry.build("oracle", target=o.target, options=o.options, seed=0, device="cpu")
    assert o.clairvoyant and not g.clairvoyant
    assert o.search.bw_logits[0] == 0.0 and sorted(o.search.bw_logits) == sorted(raw["search"]["bw_logits"])
    assert g.search == o.search == g.search_settings() == o.search_settings()   # one search for every BCD


def test_a_profile_budget_overrides_the_settings_of_its_profile_only(raw):
    cfg = copy.deepcopy(raw)
    cfg["methods"]["ins_woa"] = {**cfg["methods"]["ins_woa"], "budgets": {"smoke": {"population": 8},
                                                                        "paper": {"iterations": 80}}}
    got = {p: S.resolve({**cfg, "profile": p}).methods["ins_woa"].options for p in ("smoke", "demo", "paper")}
    base = raw["methods"]["ins_woa"]
    assert (got["smoke"].population, got["smoke"].iterations) == (8, base["iterations"])
    assert (got["demo"].population, got["demo"].iterations) == (base["population"], base["iterations"])
    assert (got["paper"].population, got["paper"].iterations) == (base["population"], 80)
    cfg["methods"]["ins_woa"]["budgets"]["smoke"] = {"popuation": 8}
    with pytest.raises(ConfigError, match=r"unknown key 'methods.ins_woa.budgets.smoke.popuation' \(expected one of "
                                          r"iterations, population, region_margin_cells\); did you mean 'population'"):
        S.resolve({**cfg, "profile": "smoke"})


def test_only_the_upper_bounds_are_clairvoyant_and_only_world_models_and_rl_methods_learn(settings):
    classes = {n: m.controller_class for n, m in settings.methods.items()}
    assert sorted(n for n, c in classes.items() if c.clairvoyant) == ["ceiling", "oracle", "perfect"]
    assert [n for n, c in classes.items() if c.places] == ["ceiling"]  # the one bound that places, not flies
    assert {settings.methods[n].table_class for n, c in classes.items() if c.clairvoyant} == {"upper bound"}
    learners = sorted(n for n, m in settings.methods.items() if m.learns)
    assert learners == sorted(["dswm", "dswm_plus", "dswm_wo_dec", "dswm_wo_unc", *LEARNING_BASELINES])
    assert [settings.methods[m].table_class for m in LEARNING_BASELINES] == list(LEARNING_BASELINES.values())


def test_unregistered_method_names_the_key_and_the_expected_form(raw):
    cfg = copy.deepcopy(raw)
    cfg["methods"]["run"] = ["static", "gredy"]
    with pytest.raises(ConfigError) as err:
        S.resolve(cfg)
    msg = str(err.value)
    assert "methods.run" in msg and "'gredy'" in msg and "greedy" in msg and "package.module:ClassName" in msg


def test_user_method_by_class_path_with_typed_options(raw, user_module):
    cfg = with_user(raw, {"hover": {"class": f"{user_module}:Hover", "options": {"bw": 0.5}}}, ["static", "hover"])
    s = S.resolve(cfg)
    assert list(s.methods) == ["static", "hover"]
    m = s.methods["hover"]
    assert (m.label, m.table_class, type(m.options).__name__) == ("Hover (user)", "deployment", "HoverOptions")
    ctrl = registry.build("hover", target=m.target, options=m.options, seed=1, device="cpu")
    assert ctrl.options.bw == 0.5 and ctrl.seed == 1
    back = S.MethodSettings.from_plain(S.evaluate_slice(s, "hover")["method"])
    assert back == m


@pytest.mark.parametrize("options, words", [({"bw": "high"}, ["methods.user.hover.options.bw", "a finite number",
                                                              "'high'"]),
                                            ({"bw": 0.5, "height": 3}, ["unknown key(s) ['height']"]),
                                            ({}, ["missing key(s) ['bw']"])])
def test_user_options_are_checked_against_the_class_settings(raw, user_module, options, words):
    cfg = with_user(raw, {"hover": {"class": f"{user_module}:Hover", "options": options}}, ["hover"])
    with pytest.raises(ConfigError) as err:
        S.resolve(cfg)
    for w in words:
        assert w in str(err.value), str(err.value)


def test_user_class_that_is_not_a_controller_or_not_importable_is_refused(raw, user_module):
    for target, words in [(f"{user_module}:NotAController", "not a subclass"),
                          ("no_such_module_xyz:Thing", "cannot import module")]:
        with pytest.raises(ConfigError) as err:
            S.resolve(with_user(raw, {"x": {"class": target}}, ["x"]))
        assert words in str(err.value) and "methods.user.x.class" in str(err.value)


def test_base_controller_refuses_what_it_does_not_implement():
    c = Controller(name="bare")
    with pytest.raises(NotImplementedError, match="does not learn"):
        c.fit(None, run_dir=".")
    with pytest.raises(NotImplementedError, match="not batched"):
        c.act_batch({"fleet": np.zeros((1, 16, 7))})
    assert Controller.options_from_plain(name="bare", data=None) is None
    with pytest.raises(ConfigError, match="declares no options_type"):
        Controller.options_from_plain(name="bare", data={"x": 1})


@pytest.mark.parametrize("profile", ["demo", "smoke", "paper"])
def test_dswm_wo_unc_and_dswm_plus_share_the_training_of_dswm_and_dswm_wo_dec_trains_alone(raw, profile):
    cfg = {**raw, "profile": profile}
    assert raw["methods"]["run"][:3] == LEARNERS
    s = S.resolve(cfg)
    assert s.training_sources() == {"dswm": "dswm", "dswm_wo_unc": "dswm", "dswm_wo_dec": "dswm_wo_dec",
                                    "dswm_plus": "dswm", **{m: m for m in s.methods if m in LEARNING_BASELINES}}
    ident = {m: registry.training_identity(s.methods[m].controller_class, s.methods[m].options) for m in LEARNERS}
    assert ident["dswm"] == ident["dswm_wo_unc"] != ident["dswm_wo_dec"]
    plus = s.methods["dswm_plus"]
    assert registry.training_identity(plus.controller_class, plus.options) == ident["dswm"]


@pytest.mark.parametrize("section, override", [("world_model", {"deter": 64}), ("training", {"lr": 3.0e-4})])
def test_a_method_that_overrides_what_shapes_training_trains_alone(raw, section, override):
    cfg = copy.deepcopy(raw)
    cfg["dswm"]["methods"]["dswm_wo_unc"][section] = override
    assert sources(cfg) == {m: m for m in LEARNERS}


def test_sharing_follows_the_settings_not_the_names(raw):
    cfg = copy.deepcopy(raw)
    cfg["dswm"]["methods"]["dswm_wo_unc"]["world_model"] = {"service_head": "mlp"}  # dswm_wo_dec's world model
    cfg["dswm"]["methods"]["dswm_wo_unc"]["planner"] = {"lambda_u": 0.0, "proposal": "none"}
    assert sources(cfg) == {"dswm": "dswm", "dswm_wo_unc": "dswm_wo_unc", "dswm_wo_dec": "dswm_wo_unc"}


def test_planner_and_evaluation_settings_do_not_rerun_training_but_world_model_settings_do(raw):
    base = S.param(S.train_slice(S.resolve(raw), "dswm"))
    cfg = copy.deepcopy(raw)
    cfg["dswm"]["planner"]["lambda_u"] = 0.5
    cfg["dswm"]["methods"]["dswm_wo_unc"]["planner"] = {"lambda_u": 0.25}
    cfg["evaluation"]["progress_mininterval_s"] = 60.0
    cfg["evaluation"]["batch_days"] = not cfg["evaluation"]["batch_days"]
    assert S.param(S.train_slice(S.resolve(cfg), "dswm")) == base
    cfg["dswm"]["world_model"]["deter"] = 64
    assert S.train_slice(S.resolve(cfg), "dswm")["method"]["options"]["world_model"]["rssm"]["deter"] == 64
    cfg = copy.deepcopy(raw)
    cfg["scenario"]["n_uavs"] = 12
    assert S.train_slice(S.resolve(cfg), "dswm")["scenario"]["n_uavs"] == 12


def test_the_first_method_in_run_order_is_the_training_source(raw):
    cfg = copy.deepcopy(raw)
    cfg["methods"]["run"] = ["static", "dswm_wo_unc", "dswm_wo_dec", "dswm"]
    assert sources(cfg) == {"dswm_wo_unc": "dswm_wo_unc", "dswm_wo_dec": "dswm_wo_dec", "dswm": "dswm_wo_unc"}
    cfg["dswm"]["planner"]["lambda_u"] = 0.5  # planning settings never split a training
    cfg["dswm"]["budgets"]["demo"]["planner"] = {"n_samples": 8, "n_elites": 2}
    assert sources(cfg)["dswm"] == "dswm_wo_unc"


def test_user_learners_train_alone_unless_their_class_shares_training(raw, user_module):
    user = {"f1": {"class": f"{user_module}:Fitter", "options": {"steps": 5, "greed": 0.1}},
            "f2": {"class": f"{user_module}:Fitter", "options": {"steps": 5, "greed": 0.1}},
            "s1": {"class": f"{user_module}:SharedFitter", "options": {"steps": 5, "greed": 0.1}},
            "s2": {"class": f"{user_module}:SharedFitter", "options": {"steps": 5, "greed": 0.2}},
            "s3": {"class": f"{user_module}:SharedFitter", "options": {"steps": 9, "greed": 0.1}}}
    assert sources(with_user(raw, user, ["static", *user])) == {"f1": "f1", "f2": "f2", "s1": "s1", "s2": "s1",
                                                               "s3": "s3"}
