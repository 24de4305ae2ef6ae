"""The one typed builder of settings, the one ``ConfigError``, and the project's stable hash.

Every settings section of ``config.yaml`` (scenario, evaluation, methods, DSWM, datasets, ...) is a frozen,
keyword-only dataclass built from its mapping by :func:`build`. Every field is required (config.yaml writes
every value out, so the code holds no second copy of a default); an unknown or missing key, or a value of the
wrong type, raises :class:`ConfigError` naming the dotted key, what was expected and what was found.

``ConfigError`` and ``build`` are defined in :mod:`prep.typed`, below both packages, so the data preparation (which
imports nothing of ``dswm``) raises and builds with the same ones; every ``dswm`` module takes them from here.
This module imports nothing else from the project: every layer may use it.

A settings field states its type (the annotation), its constraint (``setting("count")``, :func:`setting`) and its
meaning (the docstring under it) once; :func:`settings_schema` and :func:`method_schema` turn such a dataclass into the
JSON schema of its config section, so the schema of config.yaml does not repeat them.
"""
from __future__ import annotations

import ast
import copy
import dataclasses
import functools
import hashlib
import inspect
import json
import re
import textwrap
import typing
from pathlib import Path
from typing import Any, Iterable, Mapping

import yaml

from prep.typed import ENUM, FLAT, GIVEN, KINDS, SECTION, ConfigError, build, check_fields, fragment, setting

__all__ = ["ConfigError", "ENUM", "FLAT", "GIVEN", "KINDS", "SECTION", "build", "canonical_json", "check_fields",
           "field_docs", "load_yaml", "merge", "method_schema", "setting", "settings_schema", "stable_hash", "to_plain",
           "with_budget"]

PROFILE_NAME = "^[A-Za-z_][A-Za-z0-9_-]*$"
"""The names a ``budgets`` mapping accepts (profile names)."""


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


def with_budget(section: Mapping[str, Any], profile: str, key: str, *, required: bool = False) -> tuple[dict, str]:
    """A section with per-profile budgets, under ``profile``: the section less its ``budgets`` with the
    ``budgets.<profile>`` entry merged over it (:func:`merge`, mappings key by key, so a budget may set one nested
    key alone), and the key that names it in messages, ``<key> (with <key>.budgets.<profile>)`` when that entry
    exists. The one merge of every section that has budgets (``figures``, ``resources``, ``dswm``, ``search``, the
    methods').

    Args:
        section: the section as config.yaml holds it (``budgets``: {profile: {key: value}}, may be absent or null).
        profile: the selected profile.
        key: the section's dotted key (``figures``, ``methods.tdmpc``).
        required: the section must have an entry for ``profile`` (DSWM's, whose budget holds keys the section
            does not).

    Raises:
        ConfigError: ``required`` and ``budgets`` has no entry ``profile``.
    """
    section = dict(section)
    budgets = section.pop("budgets", None) or {}
    if profile not in budgets:
        if required:
            raise ConfigError(f"config.yaml: key '{key}.budgets' has no entry {profile!r} (found {sorted(budgets)})")
        return merge(section, None), key
    return merge(section, budgets[profile]), f"{key} (with {key}.budgets.{profile})"


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


# ---- the JSON schema of a settings dataclass --------------------------------------------------------------------
@functools.lru_cache(maxsize=None)
def field_docs(cls: type) -> dict[str, str]:
    """The docstring of each field of the dataclass ``cls`` (the string literal under its annotation, whitespace
    folded), its dataclass bases' included; a field without one is absent."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if not dataclasses.is_dataclass(klass):
            continue
        try:
            body = ast.parse(textwrap.dedent(inspect.getsource(klass))).body[0].body
        except (OSError, TypeError):
            continue
        for node, after in zip(body, body[1:]):
            if (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) and isinstance(after, ast.Expr)
                    and isinstance(after.value, ast.Constant) and isinstance(after.value.value, str)):
                docs[node.target.id] = " ".join(after.value.value.split())
    return docs


def _name(cls: type) -> str:
    return f"{cls.__module__}.{cls.__qualname__}"


def settings_schema(cls: type, *, partial: bool = False) -> dict:
    """The JSON schema of a config section that :func:`build` makes into the settings dataclass ``cls``.

    Each field is a property: its constraint (:func:`setting`; a name of :data:`KINDS` as ``$ref`` to the schema's
    ``$defs`` of that name, which the config schema takes from :data:`KINDS`), its docstring as ``title``; a nested
    settings dataclass (``setting(SECTION)``) is its own block, one whose keys sit in the section (``setting(FLAT)``)
    adds its properties to this block's, and a field the caller passes (``setting(GIVEN)``) is no key. ``required``:
    every key (:func:`build` requires each, a field's default serves code only); unknown keys are refused.

    Args:
        cls: a keyword-only settings dataclass whose every field states a constraint.
        partial: the block of a ``budgets.<profile>`` entry or of an override: no key required (nested sections
            alike).

    Raises:
        TypeError: a field states no constraint.
    """
    hints = typing.get_type_hints(cls)
    docs = field_docs(cls)
    props: dict[str, Any] = {}
    required = []
    for f in dataclasses.fields(cls):
        if not f.init:
            continue
        spec = f.metadata.get("setting")
        if spec is None:
            raise TypeError(f"{_name(cls)}.{f.name} states no constraint (dswm.config.setting)")
        if spec.kind == GIVEN:
            continue
        if spec.kind == FLAT:
            inner = settings_schema(hints[f.name], partial=partial)
            props.update(inner["properties"])
            required.extend(inner.get("required", []))
            continue
        if spec.ref is not None:
            prop = {"$ref": f"#/$defs/{spec.ref}"}
        elif spec.kind == SECTION:
            inner = typing.get_args(hints[f.name]) or (hints[f.name],)
            prop = settings_schema(next(a for a in inner if a is not type(None)), partial=partial)
        elif spec.kind in KINDS:
            prop = {"$ref": f"#/$defs/{spec.kind}", "description": KINDS[spec.kind]["description"]}
        else:
            prop = fragment(spec, hints[f.name])
        if f.name in docs:
            prop["title"] = docs[f.name]
        props[f.name] = prop
        required.append(f.name)
    block: dict[str, Any] = {"type": "object", "additionalProperties": False,
                             "description": f"a mapping of the settings of {_name(cls)}",
                             "x-settings-class": _name(cls), "properties": props}
    if required and not partial:
        block["required"] = required
    return block


def method_schema(cls: type) -> dict:
    """The JSON schema of a method's section ``methods.<name>`` whose settings are the dataclass ``cls``: the
    :func:`settings_schema` of ``cls`` and ``budgets``, a mapping profile -> some of the same settings (merged over
    the section by :func:`with_budget`)."""
    block = settings_schema(cls)
    budgets = {"type": "object", "additionalProperties": False,
               "description": "a mapping profile -> {setting: value} overriding these settings under that profile",
               "patternProperties": {PROFILE_NAME: settings_schema(cls, partial=True)}}
    block["properties"] = {"budgets": budgets, **block["properties"]}
    return block
