"""Observation readers (registry kind ``meteo_reader``) and the single entry point ``read_observations``."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from metegs.errors import ConfigError, DataError
from metegs.meteo.observations import ObservationTable
from metegs.meteo.readers.base import MeteoWarning, ObservationReader, Problems, decode_text
from metegs.registry import registry

__all__ = ["MeteoWarning", "ObservationReader", "Problems", "detect_reader", "parse_options", "read_observations"]

_HEAD_BYTES = 4096


def detect_reader(path: str | Path) -> str:
    """Registry name of the reader that recognises ``path``; a DataError lists the readers otherwise."""
    path = Path(path)
    if not path.is_file():
        raise DataError(path, "file does not exist" if not path.exists() else "is not a file")
    with open(path, "rb") as f:
        head = decode_text(path, f.read(_HEAD_BYTES), errors="replace")
    candidates = []
    for entry in registry("meteo_reader").entries():
        cls = entry.load()
        can = getattr(cls, "can_read", None)
        if can is not None:
            candidates.append((getattr(cls, "priority", 100), entry.name, can))
    for _, name, can in sorted(candidates):
        if can(path, head):
            return name
    raise DataError(
        path,
        "cannot tell the format of this file; choose a reader with reader=NAME (CLI: --reader NAME): "
        + ", ".join(registry("meteo_reader").names()),
    )


def parse_options(pairs: tuple[str, ...] | list[str], flag: str = "--set") -> dict[str, str]:
    """Options given as ``KEY=VALUE`` strings (reader options of ``--set``): ``("year=2024",)`` -> ``{"year": "2024"}``.

    Values stay strings; each reader converts its own. ``flag`` names the option in the error.
    """
    out = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"{flag} expects KEY=VALUE, got {pair!r}")
        out[key.strip()] = value.strip()
    return out


def read_observations(path: str | Path, reader: str | None = None, **options: Any) -> ObservationTable:
    """Read a station record or forecast file into an ObservationTable.

    ``reader`` names a registered reader (``csv``, ``metar``, ``ghcnh``, ``isd``, ``open-meteo`` or a
    plugin's); None detects it from the file name and its first few KB. ``options`` go to the reader
    (e.g. ``year=``/``month=`` for METAR, column names for csv); unknown options are a ConfigError.
    """
    path = Path(path)
    name = reader if reader is not None else detect_reader(path)
    if reader is not None and not path.exists():
        raise DataError(path, "file does not exist")
    cls = registry("meteo_reader").get(name)
    return cls().read(path, **options)
