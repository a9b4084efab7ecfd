"""Weather synthesis: degrade a scene's views with rain, fog and lens drops from θ, and write degraded datasets.

    from metegs.synth import degrade_scene
    rainy, records = degrade_scene(scene, theta, kinds="rain+fog", seed=0)

`metegs-synth` (metegs/cli/synth.py) drives it from a met record and writes a degraded copy of a dataset.
"""

from metegs.synth.degrade import KINDS, DegradedView, degrade_scene, iter_degraded_views, parse_kinds

__all__ = ["KINDS", "DegradedView", "degrade_scene", "iter_degraded_views", "parse_kinds"]
