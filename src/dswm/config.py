"""The one typed builder of settings, the one ``ConfigError``, and the project's stable hash.

Every settings section of ``config.yaml`` (scenario, evaluation, methods, DSWM, datasets, ...) is a frozen,
keyword-only dataclass built from its mapping by :func:`build`. Every field is required (config.yaml writes
every value out, so the code holds no second copy of a default); an unknown or missing key, or a value of the
wrong type, raises :class:`ConfigError` naming the dotted key, what was expected and what was found.

This module imports nothing from the rest of the project: every layer may use it.
"""
from __future__ import annotations

import copy
import dataclasses
import hashlib
import json
import math
import re
import types
import typing
from pathlib import Path
from typing import Any, Iterable, Literal, Mapping

import yaml


class ConfigError(ValueError):
    """A configuration value is missing, unknown or of the wrong form; the message names the key."""


def stable_hash(obj: Any, *, length: int = 16) -> str:
    """Hash of a JSON-serialisable object that does not depend on key order.

    Args:
        obj: nested dicts/lists of numbers, strings, booleans and None (dataclasses are converted).
        length: number of hex digits kept.

    Returns:
        A hex digest prefix, identical across runs and machines for equal inputs.
    """
    if dataclasses.is_dataclass(obj):
        obj = dataclasses.asdict(obj)
    text = json.dumps(obj, sort_keys=True, separators=(",", ":"), default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:length]


def canonical_json(obj: Any) -> str:
    """``obj`` (dataclasses converted) as JSON with sorted keys: equal settings give equal text, whatever the
    key order of the YAML they came from (the form of every rule's ``params``)."""
    return json.dumps(to_plain(obj), sort_keys=True, separators=(",", ":"))


def to_plain(obj: Any) -> Any:
    """Dataclasses as dicts and tuples as lists, recursively (what :func:`build` accepts back)."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, Mapping):
        return {str(k): to_plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_plain(v) for v in obj]
    return obj


def merge(base: Mapping[str, Any], over: Mapping[str, Any] | None) -> dict:
    """``over`` merged into a deep copy of ``base``, mappings key by key (e.g. a method's overrides)."""
    out = copy.deepcopy(dict(base))
    for k, v in (over or {}).items():
        out[k] = merge(out[k], v) if isinstance(v, Mapping) and isinstance(out.get(k), Mapping) else copy.deepcopy(v)
    return out


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


def load_yaml(path: str | Path) -> dict:
    """Read a YAML config file as a plain dict (its validation is :mod:`dswm.settings`' job)."""
    path = Path(path)
    try:
        with path.open() as fh:
            data = yaml.safe_load(fh)
    except FileNotFoundError as err:
        raise ConfigError(f"{path}: config file not found") from err
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping at the top level, found {type(data).__name__}")
    return data


def _parts(key: str | Iterable[Any]) -> list[Any]:
    """The path of a dotted key (``profiles.demo.seeds.milan[0]``) or of a path given as parts."""
    if not isinstance(key, str):
        return list(key)
    return [int(p) if p.isdigit() else p for p in re.findall(r"[^.\[\]]+", key)]


def lookup(data: Any, path: Iterable[Any]) -> tuple[bool, Any]:
    """(True, the value) at ``path`` of nested mappings and lists; (False, None) where there is none."""
    node = data
    for part in path:
        if isinstance(node, Mapping) and part in node:
            node = node[part]
        elif isinstance(node, list) and isinstance(part, int) and 0 <= part < len(node):
            node = node[part]
        else:
            return False, None
    return True, node


@dataclasses.dataclass(frozen=True)
class ConfigSources:
    """Where each value of the merged config came from, for messages: the workflow's ``config.yaml``, a
    ``--configfile`` (named as given) or ``--config``.

    Snakemake merges them in that order (mappings key by key, anything else replaced), so a value comes from the
    last layer that holds its path.
    """

    layers: tuple[tuple[str, Any], ...] = ()
    """(name, the layer's data), in the order Snakemake applies them over ``base``."""
    base: str = "config.yaml"

    CLI = "--config"

    def of(self, key: str | Iterable[Any]) -> str:
        """The name of the layer the value at ``key`` came from."""
        path = _parts(key)
        for name, data in reversed(self.layers):
            if lookup(data, path)[0]:
                return name
        return self.base

    def relabel(self, text: str) -> str:
        """``text`` (a message of one or more lines) with each line's leading ``config.yaml:`` replaced by the layer of
        the first key the line names (``key 'a.b'``)."""
        def one(line: str) -> str:
            if not line.startswith("config.yaml: "):
                return line
            named = re.search(r"\bkeys? '([^']+)'", line)
            return line if named is None else self.of(named.group(1)) + line[len("config.yaml"):]

        return "\n".join(one(line) for line in text.split("\n"))
