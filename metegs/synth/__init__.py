"""Degraded datasets: `metegs-synth`'s pipeline (a scene, its depth, θ from a met record or explicit values, the
weather applied by `metegs.weather.degrade`, a copy written in the scene's own format with the clean images
alongside, weather.json and a contact sheet).

The weather itself is applied in memory by `metegs.weather.degrade.degrade_scene` (used by training's
``--degrade``); this package writes it out.
"""
