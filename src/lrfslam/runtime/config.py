"""Layered configuration for frozen config dataclasses.

Precedence, lowest first: dataclass defaults < the config file (TOML) < the
environment < ``--set name=value`` flags. Nested dataclasses are addressed with
dots (``histogram.bin_deg``), as TOML sub-tables, and in the environment with a
double underscore (``LRFSLAM_DENOISE_HISTOGRAM__BIN_DEG``).

Only a config's *settings* can be set: the dotted names in its ``SETTINGS`` class
attribute (every leaf field when it has none). The other fields are the
algorithms' fixed parameters: the effective configuration (``to_json``, kept in
every recording) shows them, tests construct them, an operator does not tune
them. Any other name is an error, so a typo fails at start-up instead of
silently running defaults, in one line: a retired setting's line says what
replaced it (the class's ``RETIRED``), a fixed parameter's its value, an unknown
name the nearest setting. ``docs/settings.md`` documents every setting.
"""

from __future__ import annotations

import dataclasses
import difflib
import json
import tomllib
import types
import typing
from collections.abc import Collection, Mapping
from pathlib import Path
from typing import Any, TypeVar

from lrfslam.errors import ConfigError

C = TypeVar("C")
ENV_PREFIX = "LRFSLAM"


def read_file(path: str | Path | None, tables: Collection[str] | None = None) -> dict:
    """The parsed TOML file, or ``{}`` when no path is given.

    With ``tables``, a top-level table of another name is an error (a misspelt or
    renamed service must not silently run on defaults), with the nearest name as a hint.
    """
    if not path:
        return {}
    try:
        with open(path, "rb") as f:
            parsed = tomllib.load(f)
    except OSError as exc:
        raise ConfigError(f"cannot read config file {path}: {exc.strerror}") from exc
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"config file {path}: {exc}") from exc
    for name in parsed if tables is not None else ():
        if name not in tables:
            near = difflib.get_close_matches(name, list(tables), n=1)
            hint = f" (did you mean [{near[0]}]?)" if near else ""
            raise ConfigError(f"config file {path}: unknown table [{name}]{hint}; "
                              f"known: {', '.join(sorted(tables))}")
    return parsed


def coerce(value: Any, hint: Any, name: str) -> Any:
    """Convert ``value`` (from TOML, env or a flag) to the field type ``hint``."""
    origin = typing.get_origin(hint)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(hint) if a is not type(None)]
        if value is None or (isinstance(value, str) and value.lower() in ("", "none", "null")):
            return None
        return coerce(value, args[0], name)
    if origin is tuple:
        args = typing.get_args(hint)
        if isinstance(value, str):
            value = json.loads(value) if value.strip().startswith("[") else [v for v in value.split(",") if v]
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{name}: expected a list, got {value!r}")
        item = args[0] if args else str
        return tuple(coerce(v, item, name) for v in value)
    try:
        if hint is bool:
            if isinstance(value, str):
                low = value.strip().lower()
                if low not in ("1", "0", "true", "false", "yes", "no", "on", "off"):
                    raise ValueError(value)
                return low in ("1", "true", "yes", "on")
            return bool(value)
        if hint is int:
            if isinstance(value, float) and not value.is_integer():
                raise ValueError(value)
            return int(value)
        if hint is float:
            return float(value)
        if hint is str:
            return str(value)
        if hint is Path:
            return Path(value)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{name}: cannot use {value!r} as {getattr(hint, '__name__', hint)}") from exc
    return value


def _flatten(table: Mapping, prefix: str = "") -> dict[str, Any]:
    flat: dict[str, Any] = {}
    for k, v in table.items():
        if isinstance(v, Mapping):
            flat.update(_flatten(v, f"{prefix}{k}."))
        else:
            flat[f"{prefix}{k}"] = v
    return flat


def _fields(cls: type, prefix: str = "") -> dict[str, tuple[Any, Any]]:
    """Dotted field name -> (type hint, default) for every leaf field of ``cls``."""
    hints = typing.get_type_hints(cls)
    out: dict[str, tuple[Any, Any]] = {}
    for f in dataclasses.fields(cls):
        hint = hints[f.name]
        if dataclasses.is_dataclass(hint):
            out.update(_fields(hint, f"{prefix}{f.name}."))
        else:
            out[f"{prefix}{f.name}"] = (hint, f.default)
    return out


def settings(cls: type) -> dict[str, Any]:
    """Dotted name -> default of every setting of config class ``cls`` (its ``SETTINGS``, else every leaf field)."""
    names = getattr(cls, "SETTINGS", None)
    fields = _fields(cls)
    missing = [n for n in names or () if n not in fields]
    if missing:
        raise ConfigError(f"{cls.__name__}.SETTINGS names no field: {', '.join(missing)}")
    default = cls()
    out = {}
    for name in fields if names is None else names:
        value = default
        for part in name.split("."):
            value = getattr(value, part)
        out[name] = value
    return out


def _refuse(cls: type, name: str, layer: str) -> ConfigError:
    """The one-line error for ``name`` (given in ``layer``), which is not a setting of ``cls``."""
    retired = getattr(cls, "RETIRED", {})
    fields = _fields(cls)
    if name in retired:
        return ConfigError(f"{name!r} ({layer}) is no longer a setting: {retired[name]}")
    if name in fields:
        return ConfigError(f"{name!r} ({layer}) is a fixed parameter ({fields[name][1]!r}), not a setting "
                           "(docs/settings.md lists the settings)")
    near = difflib.get_close_matches(name, list(settings(cls)), n=1)
    hint = f"; did you mean {near[0]!r}?" if near else " (docs/settings.md lists the settings)"
    return ConfigError(f"unknown setting {name!r} ({layer}){hint}")


def _build(cls: type, values: Mapping[str, Any], prefix: str = "", base: Any = None) -> Any:
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for f in dataclasses.fields(cls):
        hint = hints[f.name]
        sub_base = getattr(base, f.name) if base is not None else None
        if dataclasses.is_dataclass(hint):
            kwargs[f.name] = _build(hint, values, f"{prefix}{f.name}.", sub_base)
        elif f"{prefix}{f.name}" in values:
            kwargs[f.name] = values[f"{prefix}{f.name}"]
        elif base is not None:
            kwargs[f.name] = sub_base
    try:
        return cls(**kwargs)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{cls.__name__}: {exc}") from exc


def load(cls: type[C], *, table: Mapping | None = None, env: Mapping[str, str] | None = None,
         env_prefix: str = "", sets: typing.Iterable[str] = (), base: C | None = None) -> C:
    """Build a ``cls`` instance from the layers.

    Parameters
    ----------
    cls : frozen dataclass type
    table : mapping
        The file's table for this config (already selected, e.g. ``file["slam"]``).
    env : mapping
        Environment; keys ``<env_prefix>_<FIELD>`` (upper case, ``__`` for dots) are read.
    env_prefix : str
        e.g. ``LRFSLAM_SLAM``; empty disables the environment layer.
    sets : iterable of ``"name=value"``
        Command-line overrides, dotted names for nested fields.
    base : cls, optional
        Start from this instance instead of the dataclass defaults (e.g. a mode preset).
    """
    public = settings(cls)
    fields = _fields(cls)
    values: dict[str, Any] = {}
    for layer, items in (("config file", _flatten(table or {}).items()), ("--set", _parse_sets(sets))):
        if layer == "--set" and env is not None and env_prefix:
            for name in public:
                var = f"{env_prefix}_{name.replace('.', '__').upper()}"
                if var in env:
                    values[name] = coerce(env[var], fields[name][0], var)
        for name, raw in items:
            if name not in public:
                raise _refuse(cls, name, layer)
            values[name] = coerce(raw, fields[name][0], name)
    return _build(cls, values, base=base)


def peek(cls: type, name: str, *, table: Mapping | None = None, env: Mapping[str, str] | None = None,
         env_prefix: str = "", sets: typing.Iterable[str] = ()) -> Any:
    """The layered value of top-level field ``name`` alone, without building the whole config.

    Used to pick a preset (e.g. ``mode``) before the other values, which may only
    be valid on top of that preset, are applied.
    """
    hint, value = _fields(cls)[name]
    if table and name in table:
        value = coerce(table[name], hint, name)
    var = f"{env_prefix}_{name.upper()}"
    if env is not None and env_prefix and var in env:
        value = coerce(env[var], hint, var)
    for key, raw in _parse_sets(sets):
        if key == name:
            value = coerce(raw, hint, name)
    return value


def service_config(spec: Any, *, sets: typing.Iterable[str] = (), file: Mapping | None = None,
                   env: Mapping[str, str] | None = None) -> Any:
    """The config of service ``spec``: defaults (or its ``mode`` preset) < ``file[<service>]``
    < ``LRFSLAM_<SERVICE>_*`` in ``env`` < ``sets``.

    Parameters
    ----------
    spec : lrfslam.runtime.step.ServiceSpec
    sets : iterable of ``"name=value"``
        The service's own names (``histogram.bin_deg=10``), no service prefix.
    file : mapping
        The whole parsed config file (its ``[<service>]`` table is used); None: no file.
    env : mapping
        Environment variables; None: no environment layer.
    """
    layers = {"table": (file or {}).get(spec.name, {}), "env": env,
              "env_prefix": f"{ENV_PREFIX}_{spec.name.upper()}", "sets": list(sets)}
    base = spec.preset(peek(spec.config_type, "mode", **layers)) if spec.preset else None
    return load(spec.config_type, base=base, **layers)


def by_service(sets: typing.Iterable[str], names: typing.Iterable[str]) -> dict[str, list[str]]:
    """Split ``SERVICE.NAME=VALUE`` items by service: ``{"features": ["mode=paper"], ...}``, every name a key.

    The one reading of the commands that configure several services (``up``, ``pipeline``,
    ``eval``); a service outside ``names`` or a missing prefix is a :class:`ConfigError`.
    """
    names = tuple(names)
    out: dict[str, list[str]] = {n: [] for n in names}
    for item in sets:
        service, dot, rest = item.partition(".")
        if not dot or service not in out:
            raise ConfigError(f"--set {item!r}: expected SERVICE.NAME=VALUE with SERVICE one of {', '.join(names)}")
        out[service].append(rest)
    return out


def _parse_sets(sets: typing.Iterable[str]) -> list[tuple[str, str]]:
    out = []
    for item in sets:
        name, eq, value = item.partition("=")
        if not eq:
            raise ConfigError(f"--set expects name=value, got {item!r}")
        out.append((name.strip(), value.strip()))
    return out


def to_json(cfg: Any) -> str:
    """The effective configuration as JSON, for status replies and recording metadata."""
    return json.dumps(dataclasses.asdict(cfg), default=str, sort_keys=True)
