"""A method setting is stated once in code: the settings dataclass's field gives its type, its constraint
(``dswm.config.setting``) and its meaning (its docstring); the schema's block of the method is generated from it."""
import copy
import dataclasses
import re
import typing

import jsonschema
import pytest
import yaml

from dswm import settings as S
from dswm.config import (FLAT, GIVEN, KINDS, SECTION, ConfigError, build, check_fields, field_docs, load_yaml, merge,
                         method_schema, setting, settings_schema, with_budget)
from dswm.methods import registry
from dswm.methods.base import Controller
from dswm.methods.collect import CollectSettings
from dswm.methods.dswm.planner import PlannerConfig
from dswm.methods.dswm.rssm import RSSMConfig
from dswm.methods.dswm.settings import DSWMBudget
from dswm.methods.dswm.training import TrainConfig
from dswm.methods.dswm.world_model import WorldModelConfig
from dswm.methods.search import SearchSettings, configured_search

from conftest import ROOT

SCHEMA = S.load_schema(S.SCHEMA)
RAW = yaml.safe_load(S.SCHEMA.read_text())
GENERATED = ["ins_woa", "jtoratc", "ppo", "sac", "tdmpc", "maddpg", "ga_matr", "emorl_tcto", "hrl_tpra"]
"""The methods whose config section is generated from their settings dataclass."""


def settings_class(method):
    return registry.load_class(registry.BUILTIN[method].target).options_type


def classes_of(cls):
    """``cls`` and the nested settings dataclasses of its ``setting(SECTION)`` fields."""
    hints = typing.get_type_hints(cls)
    nested = [hints[f.name] for f in dataclasses.fields(cls) if f.metadata["setting"].kind == SECTION]
    return [cls, *(c for n in nested for c in classes_of(n))]


@pytest.fixture(scope="module")
def config():
    return load_yaml(ROOT / "config.yaml")


def validator_of(block):
    return jsonschema.Draft202012Validator({"$defs": SCHEMA["$defs"], **block})


def test_each_marker_names_its_methods_settings_class_and_the_schema_holds_the_generated_block():
    markers = {name: node for name, node in RAW["properties"]["methods"]["properties"].items()
               if isinstance(node, dict) and "x-settings" in node}
    assert sorted(markers) == sorted(GENERATED)
    for method in GENERATED:
        cls = settings_class(method)
        assert S.settings_class(markers[method]["x-settings"]) is cls
        block = SCHEMA["properties"]["methods"]["properties"][method]
        assert block == method_schema(cls)
        assert f"{cls.__module__}.{cls.__qualname__}" in block["description"]
        assert block["required"] == [f.name for f in dataclasses.fields(cls)]
        assert block["additionalProperties"] is False


@pytest.mark.parametrize("method", GENERATED)
def test_the_generated_block_takes_the_config_section_and_every_profiles_budget(config, method):
    block = SCHEMA["properties"]["methods"]["properties"][method]
    section = config["methods"][method]
    validator_of(block).validate(section)
    [partial] = block["properties"]["budgets"]["patternProperties"].values()
    assert "required" not in partial and partial["properties"].keys() == block["properties"].keys() - {"budgets"}
    for profile, budget in (section.get("budgets") or {}).items():
        validator_of(partial).validate(budget)
    for profile in config["profiles"]:                               # the merged section is complete
        merged, where = with_budget(section, profile, f"methods.{method}")
        validator_of(block).validate(merged)
        assert dataclasses.is_dataclass(build(settings_class(method), merged, where))


def first_count(cls):
    return next(f.name for f in dataclasses.fields(cls) if f.metadata["setting"].kind == "count")


@pytest.mark.parametrize("method", GENERATED)
def test_a_wrong_value_is_refused_with_its_key_the_expected_form_and_what_was_found(config, method):
    key = first_count(settings_class(method))
    bad = copy.deepcopy(config)
    bad["methods"][method][key] = 0
    bad["methods"][method].setdefault("budgets", {}).setdefault("smoke", {})[key] = "many"
    with pytest.raises(ConfigError) as err:
        S.validate_config(bad, SCHEMA)
    assert sorted(str(err.value).split("\n")[1:]) == sorted([
        f"config.yaml: key 'methods.{method}.budgets.smoke.{key}' must be an integer >= 1; found 'many'",
        f"config.yaml: key 'methods.{method}.{key}' must be an integer >= 1; found 0"])
    bad = copy.deepcopy(config)
    del bad["methods"][method][key]
    bad["methods"][method]["no_such_key"] = 1
    with pytest.raises(ConfigError) as err:
        S.validate_config(bad, SCHEMA)
    missing, unknown = sorted(str(err.value).split("\n")[1:])
    cls = settings_class(method)
    assert missing == f"config.yaml: missing key 'methods.{method}.{key}' (expected an integer >= 1)"
    allowed = ", ".join(sorted(["budgets", *(f.name for f in dataclasses.fields(cls))]))
    assert unknown == (f"config.yaml: unknown key 'methods.{method}.no_such_key' (expected one of {allowed}); a new "
                       f"setting is a field of {cls.__module__}.{cls.__qualname__}")


@pytest.mark.parametrize("method", GENERATED)
def test_the_builder_refuses_what_the_schema_refuses_naming_the_key(config, method):
    cls = settings_class(method)
    key = first_count(cls)
    merged, where = with_budget(config["methods"][method], "smoke", f"methods.{method}")
    with pytest.raises(ConfigError) as err:
        build(cls, {**merged, key: 0}, where)
    assert str(err.value) == f"config key {where}.{key}: expected an integer >= 1, found 0"
    with pytest.raises(ConfigError) as err:                          # made in code: the same check
        dataclasses.replace(build(cls, merged, where), **{key: 0})
    assert re.fullmatch(rf"config key methods\.{method}\.{key}: expected an integer >= 1, found 0", str(err.value))


@pytest.mark.parametrize("method", ["sac", "maddpg"])
def test_a_matmul_dtype_outside_its_literal_is_refused_by_the_schema_the_builder_and_in_code(config, method):
    bad = copy.deepcopy(config)
    bad["methods"][method]["matmul_dtype"] = "float16"
    with pytest.raises(ConfigError) as err:
        S.validate_config(bad, SCHEMA)
    assert str(err.value).split("\n")[1:] == [
        f"config.yaml: key 'methods.{method}.matmul_dtype' must be float32 or bfloat16; found 'float16'"]
    cls = settings_class(method)
    merged, where = with_budget(config["methods"][method], "smoke", f"methods.{method}")
    with pytest.raises(ConfigError) as err:
        build(cls, {**merged, "matmul_dtype": "float16"}, where)
    assert str(err.value) == (f"config key {where}.matmul_dtype: expected one of ['float32', 'bfloat16'], "
                              f"found 'float16'")
    with pytest.raises(ConfigError) as err:                          # made in code: the field's ENUM constraint
        dataclasses.replace(build(cls, merged, where), matmul_dtype="float16")
    assert str(err.value) == f"config key methods.{method}.matmul_dtype: expected float32 or bfloat16, found 'float16'"


def test_no_setting_of_a_generated_method_is_written_in_the_schema_file():
    text = S.SCHEMA.read_text()
    methods_raw = RAW["properties"]["methods"]

    def keys(node):
        if isinstance(node, dict):
            return set(node) | {k for sub in node.values() for k in keys(sub)}
        return {k for sub in node for k in keys(sub)} if isinstance(node, list) else set()
    in_methods = keys(methods_raw)
    elsewhere = keys({k: v for k, v in RAW.items() if k != "properties"}) | keys(
        {k: v for k, v in RAW["properties"].items() if k != "methods"})   # gamma, horizon, ... name other settings
    for method in GENERATED:
        assert set(methods_raw["properties"][method]) == {"x-settings"}
        for cls in classes_of(settings_class(method)):
            fields = {f.name for f in dataclasses.fields(cls)}
            assert fields & in_methods == set(), method
            unique = sorted(n for n in fields - elsewhere if re.search(rf"^\s*{n}:", text, re.M))
            assert unique == [], (method, unique)
    assert not set(KINDS) & set(RAW["$defs"])      # the vocabulary is stated in prep.typed.KINDS only
    assert "tdmpc_precollect" not in RAW["$defs"]


@pytest.mark.parametrize("method", GENERATED)
def test_every_field_states_a_constraint_and_a_one_line_meaning(method):
    for cls in classes_of(settings_class(method)):
        docs = field_docs(cls)
        for f in dataclasses.fields(cls):
            assert "setting" in f.metadata, f"{cls.__qualname__}.{f.name} states no constraint"
            assert docs.get(f.name), f"{cls.__qualname__}.{f.name} has no docstring"
        props = settings_schema(cls)["properties"]
        assert all(props[f.name]["title"] == docs[f.name] for f in dataclasses.fields(cls))


@dataclasses.dataclass(frozen=True, kw_only=True)
class StrideOptions:
    """A user method's options with constraints."""

    stride: int = setting("count")
    """Slots between two moves."""
    share: float = setting(schema={"type": "number", "minimum": -1, "maximum": 1, "description": "a number in [-1, 1]"})
    """A bandwidth logit."""
    mode: typing.Literal["hold", "move"] = setting("enum")
    """What the fleet does between moves."""


class Stride(Controller):
    options_type = StrideOptions


def test_a_user_methods_options_get_their_fields_constraints_through_the_builder(config):
    user = {"methods": {"user": {"mine": {"class": "x:Stride", "options": {"stride": 0, "share": 0.0,
                                                                            "mode": "hold"}}}}}
    with pytest.raises(ConfigError, match=r"^config key methods\.user\.mine\.options\.stride: expected an integer "
                                          r">= 1, found 0$"):
        Stride.options_from_config(name="mine", config=user, profile="smoke")
    user["methods"]["user"]["mine"]["options"].update(stride=2, share=1.5)
    with pytest.raises(ConfigError, match=r"options\.share: expected a number in \[-1, 1\], found 1\.5$"):
        Stride.options_from_config(name="mine", config=user, profile="smoke")
    user["methods"]["user"]["mine"]["options"].update(share=0.5)
    assert Stride.options_from_config(name="mine", config=user, profile="smoke") == StrideOptions(stride=2, share=0.5,
                                                                                                  mode="hold")
    with pytest.raises(ConfigError, match=r"^config key here\.share: expected a number in \[-1, 1\], found -2$"):
        check_fields(StrideOptions(stride=2, share=-2, mode="move"), "here")
    assert settings_schema(StrideOptions)["properties"]["mode"] == {"enum": ["hold", "move"],
                                                                     "description": "hold or move",
                                                                     "title": "What the fleet does between moves."}


def test_a_field_without_constraint_and_a_bad_marker_are_refused():
    @dataclasses.dataclass(frozen=True, kw_only=True)
    class Loose:
        n: int
        """A count."""

    with pytest.raises(TypeError, match=r"Loose\.n states no constraint"):
        settings_schema(Loose)
    with pytest.raises(ConfigError, match=r"x-settings 'dswm\.methods\.nowhere:Nothing': cannot import"):
        S.complete_schema({"properties": {"a": {"x-settings": "dswm.methods.nowhere:Nothing"}}})
    with pytest.raises(ConfigError, match=r"\$defs \['count'\] are the settings vocabulary"):
        S.complete_schema({"$defs": {"count": {"type": "integer"}}})
    with pytest.raises(TypeError, match="unknown kind 'counts'"):
        setting("counts")


# ---- DSWM's sections and the one search --------------------------------------------------------------------------
SECTIONS = {"dswm_world_model": WorldModelConfig, "dswm_training": TrainConfig, "dswm_planner": PlannerConfig,
            "dswm_budget": DSWMBudget, "search": SearchSettings}
"""The schema's ``$defs`` generated from DSWM's settings dataclasses and the search's (``x-form: section``)."""
PARTIALS = {"dswm_world_model_partial": WorldModelConfig, "dswm_training_partial": TrainConfig,
            "dswm_planner_partial": PlannerConfig}
"""Their ``x-form: partial`` blocks: some keys (``dswm.methods.<method>`` overrides, a budget's planner)."""
DSWM_CLASSES = [RSSMConfig, WorldModelConfig, CollectSettings, TrainConfig, PlannerConfig, DSWMBudget, SearchSettings]


def keys_of(cls):
    """The config keys of the section of ``cls``: its fields, a FLAT field's own, a GIVEN field none."""
    hints = typing.get_type_hints(cls)
    out = []
    for f in dataclasses.fields(cls):
        kind = f.metadata["setting"].kind
        out += keys_of(hints[f.name]) if kind == FLAT else [] if kind == GIVEN else [f.name]
    return out


def defs_validator(name):
    return jsonschema.Draft202012Validator({"$defs": SCHEMA["$defs"], "$ref": f"#/$defs/{name}"})


def test_dswms_and_the_search_markers_name_their_class_and_the_schema_holds_the_generated_blocks():
    for name, cls in {**SECTIONS, **PARTIALS}.items():
        form = "partial" if name in PARTIALS else "section"
        assert RAW["$defs"][name] == {"x-settings": f"{cls.__module__}:{cls.__qualname__}", "x-form": form}
        block = SCHEMA["$defs"][name]
        assert block == settings_schema(cls, partial=name in PARTIALS)
        assert sorted(block["properties"]) == sorted(keys_of(cls)) and block["additionalProperties"] is False
        assert block.get("required", []) == ([] if name in PARTIALS else keys_of(cls))
    assert "imagine_scale" in SCHEMA["$defs"]["dswm_planner"]["required"]      # a default serves code only
    assert "search" not in SCHEMA["$defs"]["dswm_planner"]["properties"]         # given: the one search
    assert {"deter", "kl_rep", "ensemble", "service_head"} <= set(SCHEMA["$defs"]["dswm_world_model"]["properties"])
    assert "rssm" not in SCHEMA["$defs"]["dswm_world_model"]["properties"]       # flat: its keys in the section
    assert SCHEMA["$defs"]["dswm_training"]["properties"]["collect_search"]["$ref"] == "#/$defs/search"


def test_dswms_sections_overrides_and_budgets_and_the_search_are_valid_and_build_under_every_profile(config):
    dswm = config["dswm"]
    for name in ("world_model", "training", "planner"):
        defs_validator(f"dswm_{name}").validate(dswm[name])
        for method, over in dswm["methods"].items():
            if over and name in over:
                defs_validator(f"dswm_{name}_partial").validate(over[name])
    defs_validator("search_budgeted").validate(config["search"])
    for candidate in config["selection"]["search_candidates"]:
        defs_validator("search").validate(candidate)
    plain = {k: v for k, v in config["search"].items() if k != "budgets"}
    assert configured_search(config, "demo") == (plain, "search") and configured_search(config, "paper")[0] == plain
    smoke, key = configured_search(config, "smoke")   # CI's weaker search, merged over the section
    assert key == "search (with search.budgets.smoke)" and smoke == {**plain, **config["search"]["budgets"]["smoke"]}
    for profile in config["profiles"]:
        section = configured_search(config, profile)[0]
        defs_validator("search").validate(section)
        assert build(SearchSettings, section, "search").bw_logits == tuple(
            sorted(map(float, section["bw_logits"]), key=abs))
    assert sorted(dswm["budgets"]) == sorted(config["profiles"])
    for profile in config["profiles"]:
        budget = dswm["budgets"][profile]
        defs_validator("dswm_budget").validate(budget)
        assert build(DSWMBudget, budget, f"dswm.budgets.{profile}").steps == budget["steps"]
        for method, over in dswm["methods"].items():                    # what resolve builds, section by section
            over = over or {}
            planner = merge(merge(dswm["planner"], budget["planner"]), over.get("planner"))
            defs_validator("dswm_planner").validate(planner)
            search = build(SearchSettings, configured_search(config, profile)[0], "search")
            built = build(PlannerConfig, planner, "dswm.planner", search=search)
            assert built.n_samples == planner["n_samples"]
            world_model = merge(dswm["world_model"], over.get("world_model"))
            defs_validator("dswm_world_model").validate(world_model)
            assert WorldModelConfig.from_flat(world_model, "dswm.world_model").service_head == world_model[
                "service_head"]
            training = merge(dswm["training"], over.get("training"))
            defs_validator("dswm_training").validate(training)
            assert build(TrainConfig, training, "dswm.training").lr == training["lr"]


def error_lines(bad):
    with pytest.raises(ConfigError) as err:
        S.validate_config(bad, SCHEMA)
    return sorted(str(err.value).split("\n")[1:])


@pytest.mark.parametrize("path, value, expected", [
    (["dswm", "world_model", "deter"], 0, "an integer >= 1"),
    (["dswm", "world_model", "service_head"], "lstm", "physics or mlp"),
    (["dswm", "training", "lr"], 0, "a positive number"),
    (["dswm", "training", "collect_policy"], "random", "lloyd or greedy"),
    (["dswm", "planner", "gamma"], 1.5, "a number in [0, 1]"),
    (["dswm", "planner", "sigma0_later"], 0, "a positive number, or null (the same as sigma0)"),
    (["dswm", "methods", "dswm_wo_unc", "planner", "lambda_u"], -1, "a number >= 0"),
    (["dswm", "methods", "dswm_wo_dec", "world_model", "ensemble"], 0, "an integer >= 1"),
    (["dswm", "budgets", "smoke", "transitions"], 0, "an integer >= 1"),
    (["dswm", "budgets", "demo", "planner", "n_samples"], "many", "an integer >= 1"),
    (["search", "lattice"], 4, "an odd integer >= 3"),
    (["search", "refine"], -1, "an integer >= 0"),
    (["search", "bw_logits"], [0.5], "[] (the demand-proportional split) or a list of bandwidth logits in [-1, 1] "
                                     "that includes 0"),
])
def test_a_wrong_dswm_or_search_value_is_refused_with_its_key_the_expected_form_and_what_was_found(
        config, path, value, expected):
    bad = copy.deepcopy(config)
    node = bad
    for part in path[:-1]:
        node = node[part]
    node[path[-1]] = value
    assert error_lines(bad) == [f"config.yaml: key '{'.'.join(path)}' must be {expected}; found {value!r}"]


def test_a_missing_or_unknown_dswm_or_search_key_is_named_with_the_class_that_declares_it(config):
    bad = copy.deepcopy(config)
    del bad["dswm"]["planner"]["imagine_scale"]
    del bad["search"]["sweeps"]
    bad["dswm"]["world_model"]["no_such_key"] = 1
    bad["dswm"]["methods"]["dswm_wo_unc"]["planner"]["horizn"] = 3
    bad["dswm"]["budgets"]["paper"]["stepz"] = 3
    allowed = ", ".join(sorted(keys_of(WorldModelConfig)))
    assert error_lines(bad) == sorted([
        "config.yaml: missing key 'dswm.planner.imagine_scale' (expected a positive number)",
        "config.yaml: missing key 'search.sweeps' (expected an integer >= 1)",
        f"config.yaml: unknown key 'dswm.world_model.no_such_key' (expected one of {allowed}); a new setting is a "
        f"field of dswm.methods.dswm.world_model.WorldModelConfig",
        "config.yaml: unknown key 'dswm.methods.dswm_wo_unc.planner.horizn' (expected one of "
        f"{', '.join(sorted(keys_of(PlannerConfig)))}); did you mean 'horizon'?",
        "config.yaml: unknown key 'dswm.budgets.paper.stepz' (expected one of planner, steps, training, transitions); did you "
        "mean 'steps'?"])


def test_the_dswm_and_search_builders_refuse_what_the_schema_refuses_naming_the_key(config):
    plain = configured_search(config, "demo")[0]
    search = build(SearchSettings, plain, "search")
    with pytest.raises(ConfigError, match=r"^config key selection\.search_candidates\[0\]\.lattice: expected an odd "
                                          r"integer >= 3, found 4$"):
        build(SearchSettings, {**plain, "lattice": 4}, "selection.search_candidates[0]")
    with pytest.raises(ConfigError, match=r"^config key search\.bw_logits: expected \[\] \(the demand-proportional "
                                          r"split\) or a list of bandwidth logits in \[-1, 1\] that includes 0, "
                                          r"found \[0\.5\]$"):
        SearchSettings(sweeps=1, lattice=3, refine=0, bw_logits=[0.5])          # made in code: the same check
    planner = build(PlannerConfig, config["dswm"]["planner"], "dswm.planner", search=search)
    with pytest.raises(ConfigError, match=r"^config key dswm\.planner\.n_samples: expected an integer >= 1, found 0$"):
        dataclasses.replace(planner, n_samples=0)
    with pytest.raises(ConfigError, match=r"^config key dswm\.planner\.imagine_scale: expected a positive number, "
                                          r"found 0$"):
        dataclasses.replace(planner, imagine_scale=0)
    world_model = WorldModelConfig.from_flat(config["dswm"]["world_model"], "dswm.world_model")
    with pytest.raises(ConfigError, match=r"^config key dswm\.world_model\.stoch: expected an integer >= 1, found 0$"):
        WorldModelConfig.from_flat({**config["dswm"]["world_model"], "stoch": 0}, "dswm.world_model")
    with pytest.raises(ConfigError, match=r"^config key dswm\.world_model\.service_head: expected one of "
                                          r"\['physics', 'mlp'\], found 'lstm'$"):
        WorldModelConfig.from_flat({**config["dswm"]["world_model"], "service_head": "lstm"}, "dswm.world_model")
    with pytest.raises(ConfigError, match=r"^config key dswm\.world_model\.service_head: expected physics or mlp, "
                                          r"found 'lstm'$"):
        dataclasses.replace(world_model, service_head="lstm")
    with pytest.raises(ConfigError, match=r"^config key dswm\.world_model\.free_bits: expected a number >= 0, "
                                          r"found -1$"):
        dataclasses.replace(world_model.rssm, free_bits=-1)
    training = build(TrainConfig, config["dswm"]["training"], "dswm.training")
    with pytest.raises(ConfigError, match=r"^config key dswm\.training\.checkpoint_every: expected an integer >= 1, "
                                          r"found 0$"):
        dataclasses.replace(training, checkpoint_every=0)
    with pytest.raises(ConfigError, match=r"^config key dswm\.budgets\.smoke\.steps: expected an integer >= 1, "
                                          r"found 0$"):
        build(DSWMBudget, {**config["dswm"]["budgets"]["smoke"], "steps": 0}, "dswm.budgets.smoke")


@pytest.mark.parametrize("cls", DSWM_CLASSES, ids=lambda c: c.__qualname__)
def test_every_dswm_and_search_field_states_a_constraint_and_a_one_line_meaning(cls):
    docs = field_docs(cls)
    for f in dataclasses.fields(cls):
        assert "setting" in f.metadata, f"{cls.__qualname__}.{f.name} states no constraint"
        assert docs.get(f.name), f"{cls.__qualname__}.{f.name} has no docstring"
    titles = {**field_docs(RSSMConfig), **docs} if cls is WorldModelConfig else docs   # its flat keys: RSSMConfig's
    props = settings_schema(cls)["properties"]
    assert {k: p["title"] for k, p in props.items()} == {k: titles[k] for k in keys_of(cls)}


def test_no_setting_of_dswm_or_the_search_is_written_in_the_schema_file():
    text = S.SCHEMA.read_text()

    def keys(node):
        if isinstance(node, dict):
            return set(node) | {k for sub in node.values() for k in keys(sub)}
        return {k for sub in node for k in keys(sub)} if isinstance(node, list) else set()
    for name in [*SECTIONS, *PARTIALS]:
        assert set(RAW["$defs"][name]) == {"x-settings", "x-form"}
    dswm_block = keys(RAW["properties"]["dswm"])       # the section's frame: device, its sections, methods, budgets
    # the sections' names, which DSWMBudget's keys repeat
    assert dswm_block & {k for cls in DSWM_CLASSES for k in keys_of(cls)} == {"planner", "training"}
    assert set(RAW["properties"]["search"]) == {"$ref", "description"}
    elsewhere = keys({k: v for k, v in RAW["$defs"].items() if k not in {*SECTIONS, *PARTIALS}}) | keys(
        {k: v for k, v in RAW["properties"].items() if k not in ("dswm", "search", "methods")})
    for cls in DSWM_CLASSES:                           # gamma, sigma0, dataset, ... name other settings
        unique = sorted(n for n in set(keys_of(cls)) - elsewhere - {"planner", "training"}
                        if re.search(rf"^\s*{n}:", text, re.M))
        assert unique == [], (cls.__qualname__, unique)


def test_a_marker_with_an_unknown_form_or_another_key_is_refused():
    target = "dswm.methods.search:SearchSettings"
    with pytest.raises(ConfigError, match=r"x-settings 'dswm\.methods\.search:SearchSettings': x-form must be one of "
                                          r"method, section, partial; found 'whole'$"):
        S.complete_schema({"$defs": {"search": {"x-settings": target, "x-form": "whole"}}})
    with pytest.raises(ConfigError, match=r"a x-settings marker holds nothing but x-form, found \['type', "
                                          r"'x-settings'\]$"):
        S.complete_schema({"$defs": {"search": {"x-settings": target, "type": "object"}}})
    assert S.complete_schema({"$defs": {"search": {"x-settings": target, "x-form": "section"}}})["$defs"][
        "search"] == settings_schema(SearchSettings)
