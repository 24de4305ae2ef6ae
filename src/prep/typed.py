"""The one typed builder of settings and the one ``ConfigError`` of the project (``dswm.config`` hands them to every
``dswm`` module; they live here, below both packages, so the data preparation imports nothing of ``dswm``).

:func:`build` makes a frozen, keyword-only dataclass from its config mapping: every field required, no unknown key,
each value converted to its annotated type; a mistake raises :class:`ConfigError` naming the dotted key, what was
expected and what was found.
"""
from __future__ import annotations

import dataclasses
import math
import types
import typing
from typing import Any, Literal, Mapping


class ConfigError(ValueError):
    """A configuration value is missing, unknown or of the wrong form; the message names the key."""


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
        ConfigError: a key is unknown or missing, or a value does not have the annotated type.
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
    return cls(**{n: _convert(hints[n], mapping[n], f"{where}.{n}") for n in names}, **fixed)
