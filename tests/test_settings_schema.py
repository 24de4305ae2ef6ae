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
from dswm.config import (KINDS, SECTION, ConfigError, build, check_fields, field_docs, load_yaml, method_schema,
                         setting, settings_schema, with_budget)
from dswm.methods import registry
from dswm.methods.base import Controller

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
