"""Schema validation of config.yaml: every violation as one line that names the key, what was expected and what was
found; the strings ``--config`` passed read as numbers where the schema expects one.

The schema belongs to the workflow (``workflow/schemas/config.schema.yaml``, where Snakemake keeps it). :data:`SCHEMA`
is the one place in ``src/`` that names that path: the default of :func:`dswm.settings.resolve` for a caller that
passes none (the workflow passes its own).

The file holds no method's settings: a method's section is a marker ``{x-settings: "package.module:ClassName"}`` naming
its settings dataclass, and :func:`load_schema` puts the block generated from that class in its place
(``dswm.config.method_schema``: each field's type, constraint and docstring), with the constraint vocabulary
(``dswm.config.KINDS``) as the ``$defs`` of those names. A marker with ``x-form: section`` stands for a section
without ``budgets`` (``dswm.config.settings_schema``: DSWM's sections, the one ``search``), ``x-form: partial`` for
some of its keys (an override, a profile's budget). Every caller reads the schema through :func:`load_schema`.
"""
from __future__ import annotations

import copy
import dataclasses
import difflib
import importlib
import re
from pathlib import Path
from typing import Any, Iterable, Mapping

import jsonschema
import yaml

from dswm.config import KINDS, ConfigError, ConfigSources, lookup, method_schema, settings_schema

SCHEMA = Path(__file__).resolve().parents[3] / "workflow" / "schemas" / "config.schema.yaml"
"""The JSON schema of config.yaml, in the workflow beside ``src/``."""


SETTINGS_MARKER = "x-settings"
"""The key of a marker ``{x-settings: "package.module:ClassName"}``: the block of the settings dataclass it names."""
FORM = "x-form"
"""The optional second key of a marker: which block of the class (:data:`FORMS`)."""
FORMS = {"method": method_schema, "section": settings_schema,
         "partial": lambda cls: settings_schema(cls, partial=True)}
"""A marker's forms: a method's section with ``budgets`` (the default), a section, some keys of a section."""


def load_schema(path: str | Path) -> dict:
    """Read the YAML JSON-schema of config.yaml, completed (:func:`complete_schema`)."""
    with Path(path).open() as fh:
        return complete_schema(yaml.safe_load(fh), source=str(path))


def settings_class(target: str, *, source: str = "the schema") -> type:
    """The dataclass ``"package.module:ClassName"`` that a marker names."""
    module_name, _, class_name = target.partition(":")
    try:
        cls = getattr(importlib.import_module(module_name), class_name, None)
    except ImportError as err:
        raise ConfigError(f"{source}: {SETTINGS_MARKER} {target!r}: cannot import {module_name!r} ({err})") from err
    if not (isinstance(cls, type) and dataclasses.is_dataclass(cls)):
        raise ConfigError(f"{source}: {SETTINGS_MARKER} {target!r}: expected 'package.module:ClassName' of a settings "
                          f"dataclass, found {cls!r}")
    return cls


def complete_schema(schema: Mapping[str, Any], *, source: str = "the schema") -> dict:
    """``schema`` with every marker ``{x-settings: "package.module:ClassName"}`` replaced by the block generated from
    that settings dataclass (its ``x-form``, :data:`FORMS`; ``dswm.config.method_schema`` by default), and ``$defs``
    holding ``dswm.config.KINDS``.

    Raises:
        ConfigError: a marker's class cannot be imported, its form is unknown, it holds another key, or ``$defs``
            defines a name of ``KINDS`` itself (the vocabulary is stated once, in ``prep.typed``).
    """
    out = copy.deepcopy(dict(schema))
    defs = out.setdefault("$defs", {})
    clash = sorted(set(defs) & set(KINDS))
    if clash:
        raise ConfigError(f"{source}: $defs {clash} are the settings vocabulary, defined in prep.typed.KINDS only")
    defs.update(copy.deepcopy(KINDS))

    def fill(node: Any) -> Any:
        if isinstance(node, Mapping):
            if SETTINGS_MARKER in node:
                if set(node) - {SETTINGS_MARKER, FORM}:
                    raise ConfigError(f"{source}: a {SETTINGS_MARKER} marker holds nothing but {FORM}, found "
                                      f"{sorted(node)}")
                form = node.get(FORM, "method")
                if form not in FORMS:
                    raise ConfigError(f"{source}: {SETTINGS_MARKER} {node[SETTINGS_MARKER]!r}: {FORM} must be one of "
                                      f"{', '.join(FORMS)}; found {form!r}")
                return FORMS[form](settings_class(node[SETTINGS_MARKER], source=source))
            return {k: fill(v) for k, v in node.items()}
        if isinstance(node, list):
            return [fill(v) for v in node]
        return node

    return fill(out)


def _key(path: Iterable[Any]) -> str:
    """Dotted key of a path into the config, e.g. ``profiles.demo.seeds.milan[0]``."""
    out = ""
    for part in path:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out or "(top level)"


def _describe(schema: Mapping[str, Any]) -> str:
    """The expected form of a value, from the schema's description or its type keywords."""
    if "description" in schema:
        return str(schema["description"])
    if "enum" in schema:
        return "one of " + ", ".join(repr(v) for v in schema["enum"])
    kind = schema.get("type", "a value")
    kind = " or ".join(kind) if isinstance(kind, list) else kind
    bounds = [f"{word} {schema[k]}" for k, word in (("minimum", ">="), ("maximum", "<="),
                                                   ("exclusiveMinimum", ">"), ("minItems", "with at least"))
              if k in schema]
    return f"{kind}" + (f" ({', '.join(bounds)})" if bounds else "")


CREDENTIAL_KEY = re.compile(r"(?i)(^|[_-])(pass(word|wd)?|pwd|secret|token|credentials?|api[_-]?key)($|[_-])")
"""A key named like a credential (``password``, ``db_password``, ``token``, ``api_key``, ...): refused at the top level
and in the sections of :data:`CREDENTIAL_SECTIONS` (:func:`credential_errors`)."""
CREDENTIAL_SECTIONS = ("mlflow", "tracking")
"""The top-level keys under which a key named like a credential is refused at any depth: the tracking section, and the
name a user might give a new one."""
URL_USERINFO = re.compile(r"[A-Za-z][A-Za-z0-9+.-]*://[^/?#\s@]*@|[^\s/@:]+:[^\s/@]+@")
"""A URL that carries a user (and password) before its host, ``scheme://user:password@host``, or a ``user:password@``
in any string (a malformed URL too)."""
BEFORE_AT = re.compile(r"[^\s/@]+@")
"""What stands before an ``@`` up to a slash or a space: replaced by ``***`` in every value a message shows."""
CREDENTIALS_BELONG = ("a tracking server's credentials belong in the environment (MLFLOW_TRACKING_USERNAME, "
                      "MLFLOW_TRACKING_PASSWORD) or in MLflow's credentials file ~/.mlflow/credentials, never in the "
                      "config, whose values reach the jobs' params and, through --config, the command line that `ps` "
                      "shows (docs/CLUSTER.md)")
"""Where credentials go, said by every refusal of one in the config."""


def _redacted(value: Any) -> Any:
    """``value`` with the user and password of any URL in it replaced by ``***`` (a message never shows them)."""
    return BEFORE_AT.sub("***@", value) if isinstance(value, str) else value


def credential_errors(config: Mapping[str, Any]) -> dict[tuple, str]:
    """The config's places that hold credentials, each with its message (the value never shown): a URL with a user
    or password anywhere (``mlflow.tracking_uri: http://user:password@host``), and a key named like a credential
    (:data:`CREDENTIAL_KEY`) at the top level or in a section of :data:`CREDENTIAL_SECTIONS`.

    Returns:
        {path of the key: "config.yaml: key '<key>' ...; <where credentials belong>"}; empty when there is none.
    """
    found: dict[tuple, str] = {}

    def walk(node: Any, path: tuple) -> None:
        if isinstance(node, Mapping):
            for key, sub in node.items():
                named = CREDENTIAL_KEY.search(str(key)) and (not path or path[0] in CREDENTIAL_SECTIONS)
                if named:
                    found[(*path, key)] = f"is named like a credential ({key!r})"
                else:
                    walk(sub, (*path, key))
        elif isinstance(node, list):
            for i, sub in enumerate(node):
                walk(sub, (*path, i))
        elif isinstance(node, str) and URL_USERINFO.search(node):
            found[path] = "holds a URL with a user or password before its host (scheme://user:password@host)"

    walk(config, ())
    return {path: f"config.yaml: key '{_key(path)}' {what}: refused; {CREDENTIALS_BELONG}"
            for path, what in found.items()}


def _message(err: jsonschema.ValidationError, source: str) -> str:
    """One readable line for a schema violation: the key, what was expected, what was found."""
    where = _key(err.absolute_path)
    if err.validator == "additionalProperties":
        allowed = sorted(err.schema.get("properties", {}))
        unknown = sorted(set(err.instance) - set(allowed))
        lines = []
        for name in unknown:
            if err.schema.get("patternProperties"):
                pattern = ", ".join(err.schema["patternProperties"])
                lines.append(f"{source}: key '{_key([*err.absolute_path, name])}' is not a valid name "
                             f"(expected a name matching {pattern})")
                continue
            near = difflib.get_close_matches(name, allowed, n=1)
            declared = err.schema.get("x-settings-class")
            hint = (f"; did you mean '{near[0]}'?" if near else
                    f"; a new setting is a field of {declared}" if declared else
                    "; a new setting is declared in workflow/schemas/config.schema.yaml")
            lines.append(f"{source}: unknown key '{_key([*err.absolute_path, name])}' (expected one of "
                         f"{', '.join(allowed)}){hint}")
        return "\n".join(lines)
    if err.validator == "required":
        missing = err.message.split("'")[1]
        sub = err.schema.get("properties", {}).get(missing, {})
        return f"{source}: missing key '{_key([*err.absolute_path, missing])}' (expected {_describe(sub)})"
    return f"{source}: key '{where}' must be {_describe(err.schema)}; found {_redacted(err.instance)!r}"


def validate_config(config: Mapping[str, Any], schema: Mapping[str, Any], *, source: str = "config.yaml",
                    sources: ConfigSources | None = None) -> None:
    """Check ``config`` against the schema; raise ConfigError listing every violation, one per line. Credentials in
    the config (:func:`credential_errors`) are refused first, never shown, with where they belong.

    Args:
        config: the parsed config.yaml (with any ``--configfile`` and ``--config`` overrides applied).
        schema: the parsed workflow/schemas/config.schema.yaml.
        source: file name used in messages.
        sources: where each value came from (:class:`dswm.config.ConfigSources`); each line then names the layer
            of its key instead of ``source``, and a string that ``--config`` passed says so.
    """
    refused = credential_errors(config)  # first; the schema's lines on the same keys left out (no value is shown)
    validator = jsonschema.Draft202012Validator(schema)
    errors = sorted(validator.iter_errors(config), key=lambda e: (list(map(str, e.absolute_path)), e.message))
    if not errors and not refused:
        return
    keys = [_key(path) for path in refused]
    lines = [sources.relabel(line) if sources is not None else line for line in refused.values()]
    for err in errors:
        line = _message(err, source)
        if sources is not None:
            line = sources.relabel(line)
            if isinstance(err.instance, str) and sources.of(list(err.absolute_path)) == ConfigSources.CLI:
                line += (f" (--config passed it as the string {_redacted(err.instance)!r}: Snakemake reads a value "
                         f"nested in --config as a string, taken here as a number, boolean or null only where the "
                         f"schema expects one)")
        lines.extend(one for one in line.split("\n")
                     if not any(re.search(rf"key '{re.escape(k)}[.\[']", one) for k in keys))
    raise ConfigError("invalid configuration:\n" + "\n".join(lines))


def coerce_cli_strings(config: Mapping[str, Any], schema: Mapping[str, Any], cli: Mapping[str, Any]) -> dict:
    """``config`` with each string that ``--config`` passed inside a mapping (Snakemake reads nested values as
    strings: ``scenario={"n_uavs": 3}`` arrives as ``{"n_uavs": "3"}``) read as YAML where the schema refuses the
    string and YAML reads it as a number, a boolean or null; every other value as it is.

    Args:
        config: the merged config.
        schema: the JSON schema.
        cli: the ``--config`` overrides (``workflow.config_settings.config``).
    """
    out = copy.deepcopy(dict(config))
    validator = jsonschema.Draft202012Validator(schema)
    while True:
        changed = False
        for err in validator.iter_errors(out):
            path = list(err.absolute_path)
            given, value = lookup(cli, path)
            if len(path) < 2 or not given or not isinstance(value, str) or err.instance != value:
                continue
            try:
                read = yaml.safe_load(value)
            except yaml.YAMLError:
                continue
            if read is not None and not isinstance(read, (bool, int, float)):
                continue
            node = out
            for part in path[:-1]:
                node = node[part]
            node[path[-1]] = read
            changed = True
        if not changed:
            return out


