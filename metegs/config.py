"""Config base (nerfstudio pattern: ``_target`` + ``setup()``) and safe YAML save/load of config trees."""

from __future__ import annotations

import dataclasses
import hashlib
import os
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

import yaml

from metegs.errors import ConfigError
from metegs.files import atomic_write_text

C = TypeVar("C")


@dataclasses.dataclass
class InstantiateConfig:
    """A config that builds the object it describes: ``config.setup(**kwargs) -> _target(config, **kwargs)``."""

    def setup(self, **kwargs: Any) -> Any:
        target = getattr(self, "_target", None)
        if target is None:
            raise ConfigError(f"{type(self).__name__} has no _target to set up")
        if isinstance(target, str):
            from metegs.registry import Entry

            target = Entry(type(self).__name__, target).load()
        return target(self, **kwargs)


def to_dict(config: Any) -> Any:
    """A config tree as plain YAML-safe data (paths as strings, tuples as lists); private fields dropped."""
    if dataclasses.is_dataclass(config) and not isinstance(config, type):
        return {
            f.name: to_dict(getattr(config, f.name)) for f in dataclasses.fields(config) if not f.name.startswith("_")
        }
    if isinstance(config, dict):
        return {str(k): to_dict(v) for k, v in config.items()}
    if isinstance(config, (list, tuple)):
        return [to_dict(v) for v in config]
    if isinstance(config, Path):
        return str(config)
    return config


def absolute_paths(config: C) -> C:
    """A copy of a config tree with every `Path` field made absolute (resolved against the working folder)."""
    changes = {}
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if isinstance(value, Path):
            changes[f.name] = value.resolve()
        elif dataclasses.is_dataclass(value) and not isinstance(value, type):
            changes[f.name] = absolute_paths(value)
    return dataclasses.replace(config, **changes)


TRUE_WORDS, FALSE_WORDS = ("1", "true", "yes", "on"), ("0", "false", "no", "off")
"""How a yes/no option may be written as text."""


def coerce(value: Any, annotation: Any, where: str, text: bool = False) -> Any:
    """``value`` checked against (and converted to) the type ``annotation``: ints for floats, lists for tuples, strings
    for paths. ``text``: ``value`` may also be written as text, as on a command line (``3.5``, ``true``, ``none``,
    ``a,b`` for a tuple). A ConfigError names ``where`` and what was expected. The one converter of every config and
    option in metegs (YAML configs, meteorological readers' options)."""
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if annotation is Any or annotation is None:
        return value
    if origin is typing.Annotated:
        return coerce(value, args[0], where, text)
    if origin in (typing.Union, types.UnionType):
        if type(None) in args and (
            value is None or (text and isinstance(value, str) and value.lower() in ("none", "null"))
        ):
            return None
        errors = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return coerce(value, arg, where, text)
            except ConfigError as exc:
                errors.append(exc)
        raise errors[0] if len(errors) == 1 else ConfigError(f"{where}: {value!r} matches none of {annotation}")
    if origin is typing.Literal:
        if value not in args:
            raise ConfigError(f"{where}: {value!r} is not one of {', '.join(map(repr, args))}")
        return value
    if origin in (tuple, list):
        if text and isinstance(value, str):
            value = [v.strip() for v in value.split(",")] if value.strip() else []
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        if origin is tuple and args and args[-1] is not Ellipsis:
            if len(args) != len(value):
                raise ConfigError(f"{where}: expected {len(args)} values, got {len(value)}")
            return tuple(coerce(v, a, where, text) for v, a in zip(value, args))
        inner = args[0] if args else Any
        seq = [coerce(v, inner, where, text) for v in value]
        return tuple(seq) if origin is tuple else seq
    if origin is dict:
        return dict(value)
    if dataclasses.is_dataclass(annotation):
        return value
    if annotation is Path:
        return Path(value)
    if text and isinstance(value, str) and annotation in (bool, int, float):
        return _from_text(value, annotation, where)
    if annotation is float and isinstance(value, (int, float)) and not isinstance(value, bool):
        return float(value)
    if annotation is int and isinstance(value, bool):
        raise ConfigError(f"{where}: expected an integer, got {value!r}")
    if text and annotation is str and isinstance(value, (int, float)):
        return str(value)
    if isinstance(annotation, type) and not isinstance(value, annotation):
        raise ConfigError(f"{where}: expected {annotation.__name__}, got {value!r}")
    return value


def _from_text(value: str, annotation: type, where: str) -> Any:
    if annotation is bool:
        if value.lower() in TRUE_WORDS:
            return True
        if value.lower() in FALSE_WORDS:
            return False
        raise ConfigError(f"{where}: {value!r} is not true/false")
    try:
        return annotation(value)
    except ValueError:
        raise ConfigError(f"{where}: {value!r} is not a{'n integer' if annotation is int else ' number'}") from None


def apply_overrides(config: C, overrides: dict[str, Any], where: str = "") -> C:
    """A copy of ``config`` with the values of a nested dict applied; unknown keys are an error."""
    if not isinstance(overrides, dict):
        raise ConfigError(f"{where or 'config'}: expected a mapping, got {overrides!r}")
    hints = typing.get_type_hints(type(config), include_extras=True)
    names = {f.name for f in dataclasses.fields(config) if not f.name.startswith("_")}
    changes = {}
    for key, value in overrides.items():
        key = key.replace("-", "_")
        path = f"{where}.{key}" if where else key
        if key not in names:
            raise ConfigError(f"unknown config field {path!r}; fields here: {', '.join(sorted(names))}")
        current = getattr(config, key)
        if dataclasses.is_dataclass(current) and isinstance(value, dict):
            changes[key] = apply_overrides(current, value, path)
        else:
            changes[key] = coerce(value, hints[key], path)
    return dataclasses.replace(config, **changes)


def user_cache(*parts: str) -> Path:
    """``$XDG_CACHE_HOME/metegs/<parts>`` (default ``~/.cache/metegs/<parts>``): what metegs keeps between runs."""
    base = os.environ.get("XDG_CACHE_HOME") or "~/.cache"
    return Path(base).expanduser().joinpath("metegs", *parts)


def scene_cache(scene: Path, name: str, kind: str) -> Path:
    """Where metegs caches what it derives from a scene folder: ``<scene>/<name>`` when it can be written, else
    ``user_cache(kind, <digest of the scene's path>)`` (a read-only dataset is never written to)."""
    inside = Path(scene) / name
    if os.access(inside if inside.is_dir() else Path(scene), os.W_OK):
        return inside
    digest = hashlib.sha1(str(Path(scene).resolve()).encode()).hexdigest()[:16]
    return user_cache(kind, digest)


def save_yaml(config: Any, path: Path, header: dict[str, Any] | None = None) -> None:
    """Save a config tree as readable YAML (safe types only), atomically."""
    data = dict(header or {})
    data.update(to_dict(config))
    atomic_write_text(Path(path), yaml.safe_dump(data, sort_keys=False))


def load_yaml(path: Path) -> dict[str, Any]:
    """Read a YAML mapping with the safe loader; a clear error names the file on failure."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: config file not found")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML: {exc}") from exc
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: expected a mapping of config fields at the top level")
    return data
