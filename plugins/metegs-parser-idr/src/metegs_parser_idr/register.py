"""Entry point of the plugin: importing this module registers the ``idr`` parser (lazily, by a string target).

Loaded both through the entry point and ``METEGS_PLUGINS``, it registers once; an ``idr`` parser from another
package is a clash that metegs reports as a plugin warning.
"""

from metegs.registry import registry

TARGET = "metegs_parser_idr.parser:IdrParser"
DESCRIPTION = "IDR / NeuS cameras.npz or cameras_sphere.npz + image/ (DTU, BlendedMVS as prepared for NeuS)"


def _ours(target: object) -> bool:
    return target == TARGET or getattr(target, "__module__", None) == "metegs_parser_idr.parser"


_existing = registry("parser")._entries.get("idr")  # not `in`: that would start plugin discovery from inside it
if _existing is None or not _ours(_existing.target):
    registry("parser").register("idr", TARGET, description=DESCRIPTION)
