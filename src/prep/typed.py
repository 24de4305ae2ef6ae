"""The one typed builder of settings and the one ``ConfigError`` of the project (``dswm.config`` hands them to every
``dswm`` module; they live here, below both packages, so the data preparation imports nothing of ``dswm``).

:func:`build` makes a frozen, keyword-only dataclass from its config mapping: every field required, no unknown key,
each value converted to its annotated type; a mistake raises :class:`ConfigError` naming the dotted key, what was
expected and what was found.

A field may also state its constraint, :func:`setting` (``n_envs: int = setting("count")``): a name of :data:`KINDS`,
the vocabulary shared with the JSON schema of config.yaml (its ``$defs`` of those names are these), or a JSON-schema
fragment of its own. :func:`build` checks it for every dataclass it builds, :func:`check_fields` for a dataclass made
in code, and ``dswm.config.settings_schema`` writes it into the schema.
"""
from __future__ import annotations

import dataclasses
import functools
import math
import types
import typing
from typing import Any, Literal, Mapping

import jsonschema


class ConfigError(ValueError):
    """A configuration value is missing, unknown or of the wrong form; the message names the key."""


KINDS: dict[str, dict[str, Any]] = {
    "number": {"type": "number", "description": "a number"},
    "positive": {"type": "number", "exclusiveMinimum": 0, "description": "a positive number"},
    "nonnegative": {"type": "number", "minimum": 0, "description": "a number >= 0"},
    "fraction": {"type": "number", "minimum": 0, "maximum": 1, "description": "a number in [0, 1]"},
    "discount": {"type": "number", "exclusiveMinimum": 0, "maximum": 1, "description": "a number in (0, 1]"},
    "below_one": {"type": "number", "minimum": 0, "exclusiveMaximum": 1, "description": "a number in [0, 1)"},
    "open_fraction": {"type": "number", "exclusiveMinimum": 0, "exclusiveMaximum": 1,
                      "description": "a number in (0, 1)"},
    "count": {"type": "integer", "minimum": 1, "description": "an integer >= 1"},
    "natural": {"type": "integer", "minimum": 0, "description": "an integer >= 0"},
    "flag": {"type": "boolean", "description": "true or false"},
    "net_arch": {"type": "array", "minItems": 1, "items": {"type": "integer", "minimum": 1},
                 "description": "a non-empty list of hidden-layer widths >= 1, e.g. [256, 256]"},
}
"""The constraints a settings field may name: each a JSON-schema fragment with the description that messages give
as the expected form. The schema of config.yaml takes them as its ``$defs`` of the same names."""

ENUM = "enum"
"""The constraint of a ``Literal`` field: one of its values (the schema's ``enum``)."""
SECTION = "section"
"""The constraint of a nested settings dataclass: its own fields' constraints."""
FLAT = "flat"
"""A nested settings dataclass whose keys sit in the section itself, beside the other fields' (``dswm.world_model``
holds the RSSM's keys): its own fields' constraints; the section's builder makes it from those keys and passes it to
:func:`build` (``WorldModelConfig.from_flat``)."""
GIVEN = "given"
"""A field the caller passes to :func:`build` (``**fixed``), not a key of the section (DSWM's planner gets the one
``search``)."""
SPECIAL = (ENUM, SECTION, FLAT, GIVEN)
"""The constraints that are not a name of :data:`KINDS`."""


@dataclasses.dataclass(frozen=True)
class Setting:
    """What :func:`setting` records in a field's metadata (key ``"setting"``)."""

    kind: str | None = None
    """A name of :data:`KINDS` or of :data:`SPECIAL`; None with ``schema`` or ``ref``."""
    schema: Mapping[str, Any] | None = None
    """A JSON-schema fragment of this field alone, with its ``description`` (the expected form)."""
    ref: str | None = None
    """The name of a ``$defs`` entry of the config schema that describes this nested section (checked by its own
    dataclass; ``"search"``: :class:`dswm.methods.search.SearchSettings`)."""


def setting(kind: str | None = None, *, schema: Mapping[str, Any] | None = None, ref: str | None = None,
            default: Any = dataclasses.MISSING) -> Any:
    """A dataclass field whose value has the constraint ``kind`` (a name of :data:`KINDS`, :data:`ENUM` for a
    ``Literal``, :data:`SECTION` for a nested settings dataclass, :data:`FLAT`, :data:`GIVEN`), the JSON-schema
    fragment ``schema`` (with its ``description``), or is a nested section described by the config schema's
    ``$defs/<ref>``; ``default`` for one made in code (config.yaml writes every value, :func:`build` requires it).
    The field's docstring is its meaning."""
    if sum(x is not None for x in (kind, schema, ref)) != 1:
        raise TypeError("setting(): give exactly one of kind, schema and ref")
    if kind is not None and kind not in KINDS and kind not in SPECIAL:
        raise TypeError(f"setting(): unknown kind {kind!r}; expected one of {sorted(KINDS) + list(SPECIAL)}")
    if schema is not None and "description" not in schema:
        raise TypeError("setting(): a schema fragment needs a description (the expected form in messages)")
    return dataclasses.field(default=default, metadata={"setting": Setting(kind=kind, schema=schema, ref=ref)})


def _bare(tp: Any) -> Any:
    """``tp`` without ``| None``."""
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        rest = [a for a in typing.get_args(tp) if a is not type(None)]
        if len(rest) == 1:
            return rest[0]
    return tp


def _enum_words(values: Any) -> str:
    """``a or b``, ``a, b or c``."""
    words = [str(v) for v in values]
    return words[0] if len(words) == 1 else ", ".join(words[:-1]) + " or " + words[-1]


def fragment(spec: Setting, tp: Any) -> dict[str, Any] | None:
    """The JSON-schema fragment a field's value must satisfy (with ``description``), from its :class:`Setting` and
    annotated type ``tp``; None for a nested section (:data:`SECTION`, ``ref``)."""
    if spec.schema is not None:
        return dict(spec.schema)
    if spec.kind == ENUM:
        values = list(typing.get_args(_bare(tp)))
        return {"enum": values, "description": _enum_words(values)}
    if spec.kind in KINDS:
        return dict(KINDS[spec.kind])
    return None


@functools.lru_cache(maxsize=None)
def constraints(cls: type) -> tuple[tuple[str, Any], ...]:
    """(field name, a JSON-schema validator of its fragment) of every field of the dataclass ``cls`` that states a
    constraint on its value (:func:`setting`)."""
    hints = typing.get_type_hints(cls)
    out = []
    for f in dataclasses.fields(cls):
        spec = f.metadata.get("setting")
        frag = fragment(spec, hints[f.name]) if spec is not None else None
        if frag is not None:
            out.append((f.name, jsonschema.Draft202012Validator(frag)))
    return tuple(out)


def _plain(value: Any) -> Any:
    """Tuples as lists, recursively (the form JSON schema reads)."""
    return [_plain(v) for v in value] if isinstance(value, (list, tuple)) else value


def check_value(validator: Any, value: Any, where: str) -> None:
    """ConfigError naming ``where`` unless ``value`` (None passes: an optional field's absence) fits the fragment of
    ``validator`` (from :func:`constraints`)."""
    if value is not None and not validator.is_valid(_plain(value)):
        raise ConfigError(f"config key {where}: expected {validator.schema['description']}, found {value!r}")


def check_fields(obj: Any, where: str) -> None:
    """Check every field of the dataclass instance ``obj`` that states a constraint (:func:`setting`); the
    ``__post_init__`` of a settings class calls it, so one made in code is checked as one built from config.

    Raises:
        ConfigError: ``config key <where>.<field>: expected <the constraint's description>, found <value>``.
    """
    for name, validator in constraints(type(obj)):
        check_value(validator, getattr(obj, name), f"{where}.{name}")


def _kind(tp: Any) -> str:
    """A readable name of an annotated type, for messages."""
    if tp is float:
        return "a finite number"
    if tp is int:
        return "an integer"
    if tp is bool:
        return "true or false"
    if tp is str:
        return "a string"
    return str(tp).replace("typing.", "")


def _convert(tp: Any, value: Any, where: str) -> Any:
    """``value`` converted to the annotated type ``tp``; ConfigError naming ``where`` when it does not fit."""
    origin = typing.get_origin(tp)
    if dataclasses.is_dataclass(tp):
        return build(tp, value, where)
    if tp is Any:
        return value
    if origin is Literal:
        if value not in typing.get_args(tp):
            raise ConfigError(f"config key {where}: expected one of {list(typing.get_args(tp))}, found {value!r}")
        return value
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(tp)
        if value is None and type(None) in args:
            return None
        rest = [a for a in args if a is not type(None)]
        if len(rest) == 1:
            return _convert(rest[0], value, where)
        raise ConfigError(f"config key {where}: unsupported union type {tp}")
    if origin is tuple:
        args = typing.get_args(tp)
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"config key {where}: expected a list, found {value!r}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_convert(args[0], v, f"{where}[{i}]") for i, v in enumerate(value))
        if len(value) != len(args):
            raise ConfigError(f"config key {where}: expected {len(args)} items, found {len(value)} ({value!r})")
        return tuple(_convert(a, v, f"{where}[{i}]") for i, (a, v) in enumerate(zip(args, value)))
    if origin in (dict, Mapping) or tp in (dict,):
        if not isinstance(value, Mapping):
            raise ConfigError(f"config key {where}: expected a mapping, found {value!r}")
        args = typing.get_args(tp)
        if len(args) == 2:
            return {str(k): _convert(args[1], v, f"{where}.{k}") for k, v in value.items()}
        return dict(value)
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"config key {where}: expected true or false, found {value!r}")
        return value
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise ConfigError(f"config key {where}: expected a finite number, found {value!r}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"config key {where}: expected an integer, found {value!r}")
        return value
    if tp is str:
        if isinstance(value, bool) or not isinstance(value, (str, int)):
            raise ConfigError(f"config key {where}: expected a string, found {value!r}")
        return str(value)
    raise ConfigError(f"config key {where}: unsupported type {_kind(tp)}")


def build(cls: type, mapping: Any, where: str, **fixed: Any) -> Any:
    """Build the keyword-only dataclass ``cls`` from a mapping; every field required, no unknown key.

    Args:
        cls: a dataclass whose fields are annotated with the supported types (numbers, str, bool, Literal,
            tuples, optional values, mappings and nested dataclasses).
        mapping: the config section.
        where: the section's dotted key (``dswm.planner``), used in messages.
        **fixed: fields given by the caller rather than by the config (not looked up in ``mapping``).

    Raises:
        ConfigError: a key is unknown or missing, a value does not have the annotated type, or does not satisfy
            the constraint its field states (:func:`setting`).
    """
    if not isinstance(mapping, Mapping):
        raise ConfigError(f"config key {where}: expected a mapping, found {mapping!r}")
    hints = typing.get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls) if f.init and f.name not in fixed]
    unknown = sorted(set(mapping) - set(names))
    if unknown:
        raise ConfigError(f"config key {where}: unknown key(s) {unknown}; expected {names}")
    missing = [n for n in names if n not in mapping]
    if missing:
        raise ConfigError(f"config key {where}: missing key(s) {missing}")
    values = {n: _convert(hints[n], mapping[n], f"{where}.{n}") for n in names}
    for name, validator in constraints(cls):
        if name in values:
            check_value(validator, values[name], f"{where}.{name}")
    return cls(**values, **fixed)
