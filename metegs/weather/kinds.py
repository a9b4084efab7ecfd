"""Weather kinds (rain, fog, drops, and whatever plugins add, such as snow): what `--degrade`, `metegs-synth --kinds`
and the benchmark's conditions name, read from the registered weather models."""

from __future__ import annotations

from metegs.errors import ConfigError
from metegs.registry import registry

_STAGE_ORDER = {"gaussians": 0, "medium": 1, "lens": 2}
_BUILTIN_ORDER = {"rain": 0, "fog": 1, "drops": 2}


def weather_kinds() -> dict[str, list[str]]:
    """kind -> names of the registered weather models of that kind (plugins included), in the order kinds are
    written: world-space weather first (rain, snow), then media (fog), then the lens (drops)."""
    by_kind: dict[str, list[str]] = {}
    stage: dict[str, int] = {}
    for entry in registry("weather").entries():
        model = entry.load()().model_class()
        by_kind.setdefault(model.kind, []).append(entry.name)
        stage[model.kind] = max(stage.get(model.kind, 0), _STAGE_ORDER[model.stage])  # fog: a medium
    return {k: by_kind[k] for k in sorted(by_kind, key=lambda k: (stage[k], _BUILTIN_ORDER.get(k, 9), k))}


def precipitation_kinds() -> frozenset[str]:
    """Kinds that fall anew in every photo (rain, snow: a model of theirs is `transient`): θ's precipitation rate
    sets them."""
    configs = [e.load()() for e in registry("weather").entries()]
    return frozenset(c.kind for c in configs if c.model_class().transient)


def kind_of(name: str) -> str:
    """The kind of the registered weather model ``name`` (ConfigError naming the registered ones if unknown)."""
    return registry("weather").get(name)().kind


def join_kinds(kinds) -> str:
    """Kinds as one ``+``-joined word in the order of `weather_kinds` (``rain+fog``, ``snow+fog+drops``)."""
    order = list(weather_kinds())
    return "+".join(sorted(kinds, key=lambda k: order.index(k) if k in order else len(order)))


def parse_kinds(kinds: str, where: str = "kinds") -> frozenset[str]:
    """``"rain+fog"`` -> {"rain", "fog"}; a ConfigError naming ``where`` lists the registered kinds when one is
    unknown, or when only lens kinds (drops, which need weather in the air) are given."""
    parts = frozenset(k.strip().lower() for k in str(kinds).split("+") if k.strip())
    known = weather_kinds()
    lens_only = {k for k, names in known.items() if all(_stage(n) == "lens" for n in names)}
    unknown = sorted(parts - set(known))
    if unknown or not parts - lens_only:
        air = [k for k in known if k not in lens_only]
        raise ConfigError(
            f"{where}={kinds!r}: expected weather kinds joined with '+' from {', '.join(air)}"
            + (f" (with '+{'+'.join(sorted(lens_only))}' for the lens)" if lens_only else "")
            + (f"; unknown: {', '.join(unknown)}" if unknown else "")
            + " (a plugin adds its own kinds)"
        )
    return parts


def _stage(name: str) -> str:
    return registry("weather").get(name)().model_class().stage
