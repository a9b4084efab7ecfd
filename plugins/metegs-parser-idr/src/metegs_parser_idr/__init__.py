"""metegs-parser-idr: read IDR / NeuS scenes (``cameras.npz`` or ``cameras_sphere.npz`` + ``image/``) in metegs.

A data-parser plugin: installing the package registers the parser ``idr`` through the ``metegs.plugins``
entry point, and metegs detects the format from a folder's contents::

    metegs-train 3dgs --data path/to/dtu_scan24          # detected
    metegs-train 3dgs --data path/to/scene --parser idr  # forced
"""

__version__ = "0.1.0"
