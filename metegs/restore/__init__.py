"""Per-view 2D restorers for the "restore each photo, then train 3DGS" baselines (registry kind ``restorer``).

Classical: ``dcp`` (dark channel prior dehazing with guided-filter refinement, He et al. 2009/2011) and
``kang2012`` (rain-streak removal by image decomposition, Kang et al. 2012). Learned slots, run from
weights the user gives: ``restormer`` (rain) and ``dehazeformer`` (fog).

    from metegs.restore import make_restorer, restorer_for_kinds
    restorer = make_restorer("dcp")                       # or make_restorer("restormer", weights="x.ts")
    chain = restorer_for_kinds("rain+fog")                # kang2012, then dcp
    clean = chain.restore(image)                          # [H, W, 3] float32 in [0, 1]

A registered restorer is a config class (``InstantiateConfig``) whose ``setup()`` returns an object with
``name``, ``removes`` and ``restore(image)``.
"""

from __future__ import annotations

from typing import Any

from metegs.config import apply_overrides
from metegs.errors import ConfigError
from metegs.registry import registry
from metegs.restore.base import ChainRestorer, Restorer, check_image

DEFAULT_FOR_KIND: dict[str, str] = {"rain": "kang2012", "fog": "dcp"}
"""The classical restorer of each weather kind."""


def restorer_names() -> list[str]:
    """Registered restorer names (plugins included)."""
    return registry("restorer").names()


def restorer_config(name: str, options: dict[str, Any] | None = None):
    """The config of restorer ``name`` with ``options`` applied (unknown names/fields: ConfigError)."""
    if name not in registry("restorer"):
        raise ConfigError(f"unknown restorer {name!r}; available: {', '.join(restorer_names())}")
    return apply_overrides(registry("restorer").get(name)(), options or {}, where=f"restorer {name}")


def make_restorer(name: str, options: dict[str, Any] | None = None, **fields: Any) -> Restorer:
    """Set up restorer ``name`` (``options`` / ``fields``: config overrides)."""
    return restorer_config(name, {**(options or {}), **fields}).setup()


def restorer_for_kinds(
    kinds: str, names: dict[str, str] | None = None, options: dict[str, dict[str, Any]] | None = None
) -> Restorer:
    """The restorer(s) for a weather ``kinds`` string (``rain``, ``fog``, ``rain+fog``): rain first, then fog.

    ``names`` maps a kind to a restorer name (default `DEFAULT_FOR_KIND`); ``options`` maps a restorer name
    to its config overrides.
    """
    wanted = [k for k in ("rain", "fog") if k in str(kinds).split("+")]
    if not wanted:
        raise ConfigError(f"no restorer for weather kinds {kinds!r} (expected rain, fog or rain+fog)")
    chosen = {**DEFAULT_FOR_KIND, **(names or {})}
    stages = [make_restorer(chosen[k], (options or {}).get(chosen[k])) for k in wanted if chosen.get(k)]
    if not stages:
        raise ConfigError(f"no restorer chosen for {kinds!r}")
    return stages[0] if len(stages) == 1 else ChainRestorer(stages)


__all__ = [
    "DEFAULT_FOR_KIND",
    "ChainRestorer",
    "Restorer",
    "check_image",
    "make_restorer",
    "restorer_config",
    "restorer_for_kinds",
    "restorer_names",
]
