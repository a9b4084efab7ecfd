"""Range checks of config values, declared on the fields and run when a config tree is built.

A field declares its range with ``Annotated[float, Range(0)]``; `check_config` walks a config tree and raises a
`ConfigError` naming the flag as it is typed (``--optim.means-lr``), the value and the range. Every float field is
also checked finite (NaN and infinity are never a setting) unless its range allows infinity.
"""

from __future__ import annotations

import dataclasses
import math
import typing
from dataclasses import dataclass
from typing import Any

from metegs.errors import ConfigError


@dataclass(frozen=True)
class Range:
    """Allowed values of a numeric field: ``lo <= value <= hi`` (``<`` where open); None is unbounded."""

    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    allow_inf: bool = False

    def problem(self, value: float) -> str | None:
        """Why ``value`` is out of range, or None."""
        if math.isnan(value) or (math.isinf(value) and not self.allow_inf):
            return "expected a finite number"
        low = self.lo is None or (value > self.lo if self.lo_open else value >= self.lo)
        high = self.hi is None or (value < self.hi if self.hi_open else value <= self.hi)
        return None if low and high else f"expected {self.describe()}"

    def describe(self) -> str:
        parts = []
        if self.lo is not None:
            parts.append(f"{'>' if self.lo_open else '>='} {self.lo:g}")
        if self.hi is not None:
            parts.append(f"{'<' if self.hi_open else '<='} {self.hi:g}")
        return "a number " + " and ".join(parts) if parts else "a number"


NON_NEGATIVE = Range(0)
POSITIVE = Range(0, lo_open=True)
FRACTION = Range(0, 1)
"""A share of the run or a weight in [0, 1]."""


def flag(prefix: str, name: str) -> str:
    """The command-line flag of field ``name`` under ``prefix`` (``optim.``): ``--optim.means-lr``."""
    return f"--{prefix}{name.replace('_', '-')}"


def check_config(config: Any, prefix: str = "") -> None:
    """Raise ConfigError for the first field of the tree ``config`` (or item of a list field) outside its `Range`,
    or a float that is not finite."""
    hints = typing.get_type_hints(type(config), include_extras=True)
    for f in dataclasses.fields(config):
        if f.name.startswith("_"):
            continue
        value = getattr(config, f.name)
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            check_config(value, f"{prefix}{f.name.replace('_', '-')}.")
            continue
        ranges = [m for m in typing.get_args(hints.get(f.name)) if isinstance(m, Range)]
        rule = ranges[0] if ranges else Range()
        for item in value if isinstance(value, (list, tuple)) else [value]:
            if not isinstance(item, (int, float)) or isinstance(item, bool) or (isinstance(item, int) and not ranges):
                continue
            why = rule.problem(float(item))
            if why:
                raise ConfigError(f"{flag(prefix, f.name)} {item!r}: {why}")
