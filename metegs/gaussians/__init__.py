"""Scene Gaussians: parameters, spherical harmonics, initialisation and PLY I/O."""

from metegs.gaussians.model import GaussianModel, GaussianSet

__all__ = ["GaussianModel", "GaussianSet"]
