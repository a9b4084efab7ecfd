"""metegs-snow: a `snow` weather model for metegs, added through the `metegs.plugins` entry point only.

Installing the package is all it takes (``pip install ./plugins/metegs-snow``); metegs finds
`metegs_snow.register` through the entry point and `snow` joins the weather models::

    metegs-train metegs-full --weather snow fog-analytic --conditions.precip-mm-h 1.5

The physics (Gunn–Marshall size distribution, Locatelli–Hobbs fall speed and mass) is in
`metegs_snow.physics`, the per-view flake Gaussians in `metegs_snow.model`.
"""

__version__ = "0.1.0"
