"""YAML presets and dotted overrides, merged into the defaults and validated on load.

A preset is a file or the name of one packaged in jaxmripp/configs (`recipe_quick`; see
`presets`). It may name a `base` preset (a path relative to its own folder) whose values it
changes; overrides (`world.size=64`, the value parsed as YAML) apply last. Unknown keys,
mistyped values and values out of range raise `ConfigError` with one line.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import typing
from pathlib import Path
from typing import Any

import yaml

from jaxmripp.config import presets
from jaxmripp.config.errors import ConfigError, shown
from jaxmripp.config.rules import validate
from jaxmripp.config.sections import Config
from jaxmripp.spec import removed

_MAX_BASE_DEPTH = 8  # `base` presets nested deeper than this are refused (cycles)
# Keys removed from the configuration, readable at their built-in value only
# (jaxmripp.spec.removed).
REMOVED: dict[str, Any] = removed.BUILT_IN


def _coerce_tuple(key: str, value: Any, annotation) -> tuple:
    """A YAML list (or one value, for tuple[x, ...]) as the annotated tuple type."""
    args = typing.get_args(annotation)
    if not isinstance(value, (list, tuple)):
        value = [value] if args[-1] is Ellipsis else value
    if not isinstance(value, (list, tuple)):
        raise ConfigError(f"{key}: got {value!r}; allowed: a list")
    items = args[:1] * len(value) if args[-1] is Ellipsis else args
    if len(items) != len(value):
        raise ConfigError(f"{key}: got {list(value)!r}; allowed: a list of {len(items)} values")
    return tuple(_coerce(key, v, a) for v, a in zip(value, items))


def _coerce_number(key: str, value: Any, annotation) -> int | float:
    """A YAML int (or integral float) as int, or a number (or 'inf') as float."""
    if annotation is int:
        if isinstance(value, bool) or not isinstance(value, int):
            if isinstance(value, float) and value.is_integer():
                return int(value)
            raise ConfigError(f"{key}: got {value!r}; allowed: an integer")
        return value
    if isinstance(value, str) and value.strip().lower() in ("inf", ".inf", "infinity"):
        return math.inf
    if isinstance(value, str):
        # YAML 1.1 reads exponents without a dot (5e-5) as strings.
        try:
            value = float(value)
        except ValueError:
            pass
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f"{key}: got {value!r}; allowed: a number")
    if math.isnan(value):
        raise ConfigError(f"{key}: got nan; allowed: a number")
    return float(value)


def _coerce(key: str, value: Any, annotation) -> Any:
    """Converts a YAML value to the annotated type, or raises ConfigError."""
    if typing.get_origin(annotation) is tuple:
        return _coerce_tuple(key, value, annotation)
    if annotation is bool:
        if isinstance(value, bool):
            return value
        raise ConfigError(f"{key}: got {value!r}; allowed: true or false")
    if annotation in (int, float):
        return _coerce_number(key, value, annotation)
    if annotation is str:
        if not isinstance(value, str):
            raise ConfigError(f"{key}: got {value!r}; allowed: a string")
        return value
    raise TypeError(f"unsupported annotation {annotation} for {key}")


def _unknown_key(key: str, known: typing.Iterable[str]) -> ConfigError:
    """The error for an unknown key, suggesting the closest known name."""
    section, _, name = key.rpartition(".")
    close = difflib.get_close_matches(name, list(known), n=1)
    hint = f"; did you mean '{section + '.' if section else ''}{close[0]}'?" if close else ""
    return ConfigError(f"{key}: unknown key{hint} (known: {', '.join(sorted(known))})")


def _check_removed(key: str, value: Any) -> None:
    """A removed key is accepted at the value its code now builds in, else refused."""
    built_in = REMOVED[key]
    if not removed.is_built_in(key, value):
        as_yaml = lambda v: str(v).lower() if isinstance(v, bool) else shown(v)  # noqa: E731
        raise ConfigError(f"{key}: got {as_yaml(value)}, a removed setting; allowed: "
                          f"{as_yaml(built_in)} (the one built in) or leaving it out")


def _merge_section(name: str, values: Any, current: Any, cls: type) -> Any:
    """The section `current` with the keys in `values` replaced, each coerced to its type."""
    if not isinstance(values, dict):
        raise ConfigError(f"{name}: got {values!r}; allowed: a mapping of keys")
    fields = typing.get_type_hints(cls)
    changes = {}
    for key, value in values.items():
        if f"{name}.{key}" in REMOVED:
            _check_removed(f"{name}.{key}", value)
            continue
        if key not in fields:
            raise _unknown_key(f"{name}.{key}", fields)
        changes[key] = _coerce(f"{name}.{key}", value, fields[key])
    return dataclasses.replace(current, **changes)


def from_dict(data: dict[str, Any] | None, base: Config | None = None) -> Config:
    """Merges nested plain data into `base` (default: the defaults) and validates."""
    base = base or Config()
    data = data or {}
    if not isinstance(data, dict):
        raise ConfigError(f"config: got {type(data).__name__}; allowed: a mapping of sections")
    hints = typing.get_type_hints(Config)
    sections = {}
    for name, values in data.items():
        if name not in hints:
            raise _unknown_key(name, hints)
        if values is not None:
            sections[name] = _merge_section(name, values, getattr(base, name), hints[name])
    cfg = dataclasses.replace(base, **sections)
    validate(cfg)
    return cfg


def to_dict(cfg: Config) -> dict[str, dict[str, Any]]:
    """Plain nested data (lists for tuples, .inf kept) suitable for YAML."""
    out = {}
    for section in dataclasses.fields(cfg):
        values = getattr(cfg, section.name)
        out[section.name] = {
            f.name: shown(getattr(values, f.name)) for f in dataclasses.fields(values)
        }
    return out


def to_yaml(cfg: Config) -> str:
    """The whole config as YAML that `from_dict(yaml.safe_load(...))` reads back equal."""
    return yaml.safe_dump(to_dict(cfg), sort_keys=False)


def parse_override(text: str) -> tuple[list[str], Any]:
    """`world.size=64` -> (['world', 'size'], 64); the value is parsed as YAML."""
    key, sep, raw = text.partition("=")
    if not sep or "." not in key:
        raise ConfigError(f"{text}: overrides look like section.key=value (e.g. world.size=64)")
    return key.strip().split("."), yaml.safe_load(raw) if raw.strip() else None


def load(path: str | Path | None = None, overrides: typing.Sequence[str] = ()) -> Config:
    """Reads a YAML preset, a file or a packaged preset's name (which may name a `base`
    preset), and applies dotted overrides."""
    cfg = Config()
    if path is not None:
        cfg = _load_file(presets.resolve(path))
    if overrides:
        merged: dict[str, dict[str, Any]] = {}
        for text in overrides:
            keys, value = parse_override(text)
            if len(keys) != 2:
                raise ConfigError(f"{text}: overrides name exactly section.key")
            merged.setdefault(keys[0], {})[keys[1]] = value
        cfg = from_dict(merged, base=cfg)
    return cfg


def _load_file(path: Path, depth: int = 0) -> Config:
    """One preset on top of its `base` chain; errors name the file."""
    if depth > _MAX_BASE_DEPTH:
        raise ConfigError(f"{path}: 'base' presets nest too deeply")
    if not path.is_file():
        raise ConfigError(f"{path}: no such config file")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as err:
        raise ConfigError(f"{path}: not valid YAML ({err})".replace("\n", " ")) from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: a config is a mapping of sections")
    base = Config()
    if "base" in data:
        base = _load_file(path.parent / data.pop("base"), depth + 1)
    try:
        return from_dict(data, base=base)
    except ConfigError as err:
        raise ConfigError(f"{path.name}: {err}") from None
