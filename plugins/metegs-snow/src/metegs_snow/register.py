"""Entry point of the plugin: importing this module registers `snow` (lazily: nothing heavy is imported here).

Named by the ``metegs.plugins`` entry point in this package's pyproject.toml, or, without installing,
by ``METEGS_PLUGINS=metegs_snow.register``. Loaded both ways at once, it registers once; a `snow` from
another package is a clash that metegs reports as a plugin warning.
"""

from metegs.registry import registry

TARGET = "metegs_snow.model:SnowConfig"
DESCRIPTION = "per-view snowflakes from the snowfall rate (Gunn–Marshall sizes, Locatelli–Hobbs fall speed)"


def _ours(target: object) -> bool:
    return target == TARGET or getattr(target, "__module__", None) == "metegs_snow.model"


_existing = registry("weather")._entries.get("snow")  # not `in`: that would start plugin discovery from inside it
if _existing is None or not _ours(_existing.target):
    registry("weather").register("snow", TARGET, description=DESCRIPTION)
