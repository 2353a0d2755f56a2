"""Loading a configuration: defaults, then a JSON, TOML or YAML file, then ``--set`` overrides, each value
checked against its field's type (a bad value is a :class:`ConfigError` naming the dotted key).

The file's format follows its name: ``*.toml`` is TOML, ``*.yaml`` and ``*.yml`` YAML (what ROS users
write; read with PyYAML's safe loader), anything else JSON. A file that does not parse is a one-line
:class:`ConfigError` naming the format and the line.

A renamed key (:data:`~droneulator.config.site.RENAMED`, e.g. ``px4.home_lat_deg``) still loads from a
file, a ``--set`` or a dict given to :func:`from_dict`: it lands on its new key with a
:class:`DeprecationWarning` (also logged) naming the new key.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import tomllib
import types
import typing
import warnings
from pathlib import Path
from typing import Any, get_type_hints

from droneulator.config.sections import SimConfig
from droneulator.config.site import RENAMED

log = logging.getLogger(__name__)


class ConfigError(ValueError):
    """A bad option value or name; the message names the option by its dotted key (``runtime.api_port``)."""


def _coerce(value: Any, typ: Any, key: str) -> Any:
    if isinstance(typ, types.UnionType) or getattr(typ, "__origin__", None) is typing.Union:
        members = [t for t in typ.__args__ if t is not type(None)]
        if value is None and len(members) < len(typ.__args__):
            return None  # an optional field left unset
        if len(members) == 1:
            return _coerce(value, members[0], key)
        return value
    origin = getattr(typ, "__origin__", None)
    if dataclasses.is_dataclass(typ):
        if isinstance(value, typ):
            return value
        return from_dict(typ, value, f"{key}.")
    if origin in (list, tuple):
        if not isinstance(value, list | tuple):
            raise ConfigError(f"{key}: expected a list, got {value!r}")
        if origin is list:
            (inner,) = typ.__args__
            return [_coerce(v, inner, f"{key}[{i}]") for i, v in enumerate(value)]
        if len(value) != len(typ.__args__):
            raise ConfigError(f"{key}: expected {len(typ.__args__)} values, got {len(value)}")
        pairs = enumerate(zip(value, typ.__args__, strict=True))
        return tuple(_coerce(v, t, f"{key}[{i}]") for i, (v, t) in pairs)
    if typ is bool and isinstance(value, str):
        if value.lower() in ("1", "true", "yes", "on"):
            return True
        if value.lower() in ("0", "false", "no", "off"):
            return False
        raise ConfigError(f"{key}: not a boolean: {value!r}")
    if typ in (int, float, str, bool):
        if isinstance(value, dict | list | tuple) or value is None:
            raise ConfigError(f"{key}: expected {typ.__name__}, got {value!r}")
        if typ is int and isinstance(value, float) and not value.is_integer():
            raise ConfigError(f"{key}: expected an integer, got {value!r}")
        try:
            return typ(value)
        except ValueError:
            raise ConfigError(f"{key}: expected {typ.__name__}, got {value!r}") from None
    return value


def _renamed(old: str, new: str) -> None:
    message = f"config key {old} is deprecated: set {new} instead (its value is used as {new})"
    log.warning(message)
    warnings.warn(message, DeprecationWarning, stacklevel=4)


def migrate(data: dict[str, Any]) -> dict[str, Any]:
    """``data`` (a nested :class:`SimConfig` dict) with every renamed key moved to its new key, each with
    a warning; the old key and the new one both given with different values is a :class:`ConfigError`."""
    out = data
    for old, new in RENAMED.items():
        (old_section, old_key), (new_section, new_key) = old.split("."), new.split(".")
        section = out.get(old_section)
        if not isinstance(section, dict) or old_key not in section:
            continue
        if out is data:
            out = dict(data)
        out[old_section] = {k: v for k, v in section.items() if k != old_key}
        target = out.get(new_section)
        target = dict(target) if isinstance(target, dict) else {}
        value = section[old_key]
        if new_key in target and target[new_key] != value:
            raise ConfigError(
                f"{old} (deprecated) and {new} are both set, to {value!r} and {target[new_key]!r}: "
                f"set {new} only"
            )
        target[new_key] = value
        out[new_section] = target
        _renamed(old, new)
    return out


def from_dict(cls: type, data: dict[str, Any], prefix: str = "") -> Any:
    """Build dataclass ``cls`` from a (possibly partial) nested dict; unknown keys and values of the
    wrong type are :class:`ConfigError` naming the key (under ``prefix``, e.g. ``"render."``); a
    :class:`SimConfig`'s renamed keys are moved to their new keys first (:func:`migrate`)."""
    if not isinstance(data, dict):
        where = prefix.rstrip(".") or "the configuration"
        raise ConfigError(f"{where}: expected a table of {cls.__name__} options, got {data!r}")
    if cls is SimConfig:
        data = migrate(data)
    hints = get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls)]
    unknown = sorted(set(data) - set(names))
    if unknown:
        raise ConfigError(
            f"unknown {cls.__name__} option(s): {', '.join(prefix + k for k in unknown)}; "
            f"known: {', '.join(names)}"
        )
    return cls(**{k: _coerce(v, hints[k], prefix + k) for k, v in data.items()})


def to_dict(cfg: Any) -> dict[str, Any]:
    return dataclasses.asdict(cfg)


YAML_SUFFIXES = (".yaml", ".yml")


def file_format(path: str | Path) -> str:
    """``"toml"``, ``"yaml"`` or ``"json"``: the format a configuration file is read as, by its name."""
    suffix = Path(path).suffix.lower()
    return "toml" if suffix == ".toml" else "yaml" if suffix in YAML_SUFFIXES else "json"


def parse_text(text: str, fmt: str) -> Any:
    """``text`` parsed as ``fmt`` (:func:`file_format`); a syntax error is a one-line :class:`ConfigError`
    ("not valid YAML: ... at line L column C") without the file's name, which the caller adds."""
    if fmt == "toml":
        try:
            return tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise ConfigError(f"not valid TOML: {exc}") from None
    if fmt == "yaml":
        import yaml  # here, not at the top: only YAML files pay for its import (``droneulator --help``)

        try:
            return yaml.safe_load(text)
        except yaml.MarkedYAMLError as exc:
            mark = exc.problem_mark or exc.context_mark
            where = f" at line {mark.line + 1} column {mark.column + 1}" if mark is not None else ""
            what = "; ".join(str(p) for p in (exc.context, exc.problem) if p)
            raise ConfigError(f"not valid YAML: {what}{where}") from None
        except yaml.YAMLError as exc:
            raise ConfigError(f"not valid YAML: {' '.join(str(exc).split())}") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise ConfigError(f"not valid JSON: {exc.msg} at line {exc.lineno} column {exc.colno}") from None


def load_file(path: str | Path) -> dict[str, Any]:
    """The options in the JSON, TOML or YAML file ``path`` (:func:`file_format`); a syntax error or a
    file that is not a table of options is a :class:`ConfigError` naming the file."""
    path = Path(path)
    try:
        data = parse_text(path.read_text(), file_format(path))
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None
    if data is None:  # an empty YAML file (or one with only comments): no options
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a table of options, got {type(data).__name__}")
    return data


def _merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def apply_override(data: dict[str, Any], assignment: str) -> dict[str, Any]:
    """Apply one ``a.b.c=value`` override (value parsed as JSON when possible) to a config dict."""
    if "=" not in assignment:
        raise ValueError(f"override must look like section.key=value, got {assignment!r}")
    key, raw = assignment.split("=", 1)
    key = key.strip()
    if key in RENAMED:
        _renamed(key, RENAMED[key])
        key = RENAMED[key]
    try:
        value = json.loads(raw)
    except json.JSONDecodeError:
        value = raw
    node: dict[str, Any] = {}
    leaf = node
    parts = key.split(".")
    for p in parts[:-1]:
        leaf[p] = {}
        leaf = leaf[p]
    leaf[parts[-1]] = value
    return _merge(data, node)


def load_config(path: str | Path | None = None, overrides: list[str] | None = None, **top: Any) -> SimConfig:
    """Defaults, then ``path``, then ``overrides``, then keyword arguments for top-level fields."""
    data = to_dict(SimConfig())
    if path is not None:
        data = _merge(data, migrate(load_file(path)))
    for o in overrides or []:
        data = apply_override(data, o)
    data.update({k: v for k, v in top.items() if v is not None})
    return from_dict(SimConfig, data)
