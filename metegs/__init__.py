"""metegs: 3D Gaussian Splatting in rain and fog, driven by meteorological observations."""

__version__ = "0.1.0"
