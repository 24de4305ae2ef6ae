"""The run configuration of the workflow: schema validation, profile resolution and job lists.

``config.yaml`` holds every section; ``profiles:`` holds the three sizes of the same pipeline (demo, smoke,
paper). :func:`resolve` drops the profiles that are not selected and puts the selected one under ``run:``;
that resolved mapping is what every rule uses, what MLflow logs as params, and what :func:`config_hash` tags
runs with. Every check here runs while Snakemake parses the workflow, so a bad config stops the run before
any job starts, with a message that names the key and the expected form.
"""
from __future__ import annotations

import copy
import difflib
from pathlib import Path
from typing import Any, Iterable, Mapping

import jsonschema
import yaml

from dswm.config import ConfigError, stable_hash

SPLITS = ("id", "ood")


def load_schema(path: str | Path) -> dict:
    """Read the YAML JSON-schema of config.yaml."""
    with Path(path).open() as fh:
        return yaml.safe_load(fh)


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
            hint = (f"; did you mean '{near[0]}'?" if near else
                    "; a new setting is declared in workflow/schemas/config.schema.yaml")
            lines.append(f"{source}: unknown key '{_key([*err.absolute_path, name])}' (expected one of "
                         f"{', '.join(allowed)}){hint}")
        return "\n".join(lines)
    if err.validator == "required":
        missing = err.message.split("'")[1]
        sub = err.schema.get("properties", {}).get(missing, {})
        return f"{source}: missing key '{_key([*err.absolute_path, missing])}' (expected {_describe(sub)})"
    return f"{source}: key '{where}' must be {_describe(err.schema)}; found {err.instance!r}"


def validate_config(config: Mapping[str, Any], schema: Mapping[str, Any], *, source: str = "config.yaml") -> None:
    """Check ``config`` against the schema; raise ConfigError listing every violation, one per line.

    Args:
        config: the parsed config.yaml (with any ``--config`` overrides applied).
        schema: the parsed workflow/schemas/config.schema.yaml.
        source: file name used in messages.
    """
    validator = jsonschema.Draft202012Validator(schema)
    errors = sorted(validator.iter_errors(config), key=lambda e: (list(map(str, e.absolute_path)), e.message))
    if errors:
        raise ConfigError("invalid configuration:\n" + "\n".join(_message(e, source) for e in errors))


def resolve(config: Mapping[str, Any]) -> dict:
    """The resolved run configuration: the selected profile under ``run``, the other profiles dropped.

    Args:
        config: a validated config mapping with ``profile`` and ``profiles``.

    Returns:
        A new dict with every section of ``config`` except ``profiles``, plus ``run`` (the selected profile).
    """
    name = config["profile"]
    profiles = config["profiles"]
    if name not in profiles:
        raise ConfigError(f"config.yaml: key 'profile' must be one of {', '.join(profiles)}; found {name!r} "
                          f"(select one with --config profile=NAME)")
    out = {k: copy.deepcopy(v) for k, v in config.items() if k != "profiles"}
    out["run"] = copy.deepcopy(profiles[name])
    return out


def config_hash(resolved: Mapping[str, Any]) -> str:
    """Hash of the resolved config; tags every MLflow run and result of this configuration."""
    return stable_hash(resolved, length=12)


def check_profile_datasets(resolved: Mapping[str, Any]) -> None:
    """Every dataset the profile runs has a ``datasets:`` section and a seed list."""
    run = resolved["run"]
    known = set(resolved.get("datasets", {}))
    for ds in run["datasets"]:
        if known and ds not in known:
            raise ConfigError(f"config.yaml: key 'profiles.{resolved['profile']}.datasets' names {ds!r}, which has "
                              f"no section under 'datasets' (expected one of {', '.join(sorted(known))})")
        if ds not in run["seeds"]:
            raise ConfigError(f"config.yaml: key 'profiles.{resolved['profile']}.seeds.{ds}' is missing "
                              f"(expected a non-empty list of integer seeds, e.g. [0, 1])")


def check_raw_files(resolved: Mapping[str, Any], root: str | Path) -> None:
    """Every dataset with ``source: raw`` that the profile runs has its raw files on disk.

    Args:
        resolved: the resolved config.
        root: the directory the paths and globs of ``datasets.<name>.raw_files`` are relative to.
    """
    root = Path(root)
    for ds in resolved["run"]["datasets"]:
        section = resolved.get("datasets", {}).get(ds, {})
        if section.get("source") != "raw":
            continue
        for i, pattern in enumerate(section.get("raw_files", [])):
            path = Path(pattern)
            base = path if path.is_absolute() else root / path
            if any(c in str(pattern) for c in "*?["):
                anchor = Path(base.anchor)
                found = list(anchor.glob(str(base.relative_to(anchor))))
            else:
                found = [base] if base.exists() else []
            if not found:
                raise ConfigError(f"config.yaml: key 'datasets.{ds}.raw_files[{i}]' = {pattern!r} matches no file "
                                  f"under {root} (expected the published raw file(s) of {ds}; download them, or "
                                  f"set 'datasets.{ds}.source: demo')")


def seeds(resolved: Mapping[str, Any], dataset: str) -> list[int]:
    """Seeds of ``dataset`` in the selected profile."""
    return list(resolved["run"]["seeds"][dataset])


def jobs(resolved: Mapping[str, Any]) -> list[tuple[str, str, int]]:
    """Every (dataset, method, seed) evaluation job of the selected profile, in table order."""
    return [(ds, m, s) for ds in resolved["run"]["datasets"] for m in resolved["methods"]["run"]
            for s in seeds(resolved, ds)]
