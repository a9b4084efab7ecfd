"""One generic registry for every kind of component, with lazy entry-point plugin discovery.

Built-in components are registered as ``"module:attribute"`` strings, so nothing heavy is imported
until a component is used. Third-party packages register through the entry-point group
``metegs.plugins``: each entry point names a module (importing it registers its components) or a
callable taking no arguments (called once). Plugins are discovered the first time a registry is
asked for its names or for a component it does not already hold; a plugin that fails to import is
reported with a warning naming it and skipped, never breaking the CLI.

For development without installing, ``METEGS_PLUGINS="pkg.module,other.module"`` imports extra
plugin modules the same way.
"""

from __future__ import annotations

import importlib
import os
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from importlib import metadata
from typing import Any

from metegs.errors import ConfigError, PluginError

ENTRY_POINT_GROUP = "metegs.plugins"
KINDS = ("parser", "rasterizer", "weather", "method", "meteo_reader", "restorer")
"""Component kinds a name selects: losses and densification are configured by each method's typed fields
(`TrainConfig.loss`, `TrainConfig.densify`), and a plugin adds them through a method of its own."""


class PluginWarning(UserWarning):
    """A plugin could not be loaded; metegs goes on without it."""


@dataclass
class Entry:
    """A registered component: a name, where it lives, and a one-line description."""

    name: str
    target: Any
    """The object itself, or a ``"module:attribute"`` string imported on first use."""
    description: str = ""
    source: str = "metegs"
    """``metegs`` for built-ins, else the plugin (entry-point) name that registered it."""

    def load(self) -> Any:
        if isinstance(self.target, str):
            module_name, _, attr = self.target.partition(":")
            try:
                obj: Any = importlib.import_module(module_name)
                for part in attr.split(".") if attr else []:
                    obj = getattr(obj, part)
            except Exception as exc:  # noqa: BLE001 - re-raised with context
                raise PluginError(
                    f"cannot load {self.name!r} from {self.target!r} (registered by {self.source}): "
                    f"{type(exc).__name__}: {exc}"
                ) from exc
            self.target = obj
        return self.target


class Registry:
    """Named components of one kind (e.g. all data parsers)."""

    def __init__(self, kind: str):
        self.kind = kind
        self._entries: dict[str, Entry] = {}

    def register(
        self,
        name: str,
        target: Any = None,
        *,
        description: str = "",
        source: str | None = None,
        overwrite: bool = False,
    ) -> Any:
        """Register ``target`` under ``name``; without ``target`` returns a decorator."""
        if target is None:

            def decorator(obj: Any) -> Any:
                self.register(name, obj, description=description, source=source, overwrite=overwrite)
                return obj

            return decorator
        if name in self._entries and not overwrite:
            raise PluginError(
                f"{self.kind} {name!r} is already registered by {self._entries[name].source}; "
                "pass overwrite=True to replace it"
            )
        self._entries[name] = Entry(name, target, description, source or _current_source())
        return target

    def get(self, name: str) -> Any:
        """The loaded component registered under ``name``; a clear error lists what exists."""
        entry = self.entry(name)
        return entry.load()

    def entry(self, name: str) -> Entry:
        if name not in self._entries:
            ensure_plugins_loaded()
        if name not in self._entries:
            raise ConfigError(f"unknown {self.kind} {name!r}; available: {', '.join(self.names()) or '(none)'}")
        return self._entries[name]

    def names(self) -> list[str]:
        ensure_plugins_loaded()
        return sorted(self._entries)

    def entries(self) -> Iterator[Entry]:
        for name in self.names():
            yield self._entries[name]

    def __contains__(self, name: object) -> bool:
        ensure_plugins_loaded()
        return name in self._entries

    def unregister(self, name: str) -> None:
        self._entries.pop(name, None)


_REGISTRIES: dict[str, Registry] = {kind: Registry(kind) for kind in KINDS}
_loading_source: list[str] = []
_plugins_state = {"loaded": False}
failed_plugins: dict[str, str] = {}
"""Plugins that failed to load in this process: name -> reason."""


def _current_source() -> str:
    return _loading_source[-1] if _loading_source else "metegs"


def registry(kind: str) -> Registry:
    """The registry of one component kind (one of ``KINDS``)."""
    if kind not in _REGISTRIES:
        raise ConfigError(f"unknown registry kind {kind!r}; kinds: {', '.join(KINDS)}")
    return _REGISTRIES[kind]


def _load_plugin(name: str, loader: Callable[[], Any], origin: str) -> None:
    _loading_source.append(name)
    try:
        obj = loader()
        if callable(obj) and not isinstance(obj, type):
            obj()
    except Exception as exc:  # noqa: BLE001 - a broken plugin must never break metegs
        failed_plugins[name] = f"{type(exc).__name__}: {exc}"
        warnings.warn(
            f"metegs plugin {name!r} ({origin}) failed to load and is skipped: {type(exc).__name__}: {exc}",
            PluginWarning,
            stacklevel=3,
        )
    finally:
        _loading_source.pop()


def ensure_plugins_loaded(force: bool = False) -> None:
    """Import the built-ins and discover entry-point plugins once per process."""
    if _plugins_state["loaded"] and not force:
        return
    _plugins_state["loaded"] = True
    importlib.import_module("metegs.builtins")
    for ep in metadata.entry_points(group=ENTRY_POINT_GROUP):
        _load_plugin(ep.name, ep.load, f"entry point {ep.value}")
    for module_name in filter(None, (m.strip() for m in os.environ.get("METEGS_PLUGINS", "").split(","))):
        _load_plugin(module_name, lambda m=module_name: importlib.import_module(m), "METEGS_PLUGINS")
