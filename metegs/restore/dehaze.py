"""Single-image dehazing with the dark channel prior, transmission refined by the guided filter.

K. He, J. Sun, X. Tang, "Single Image Haze Removal Using Dark Channel Prior", CVPR 2009 and IEEE TPAMI
33(12):2341-2353, 2011; refinement with the guided filter of K. He, J. Sun, X. Tang, "Guided Image
Filtering", ECCV 2010 / IEEE TPAMI 35(6):1397-1409, 2013 (which replaces the soft matting of the 2009
paper). The model is the one fog is synthesised with, ``I = J·t + A·(1 − t)``:

1. dark channel ``I_dark(x) = min_{y ∈ Ω(x)} min_c I^c(y)`` over a square patch Ω;
2. airlight A: among the 0.1 % pixels with the brightest dark channel, the input pixel of highest
   intensity (sum of R, G, B);
3. coarse transmission ``t̃(x) = 1 − ω · min_{y ∈ Ω(x)} min_c I^c(y)/A^c`` with ω = 0.95 (a trace of haze
   is kept for depth perception);
4. refined transmission: ``t = GF(guide = grey image, input = t̃, r, ε)`` (``cv2.ximgproc.guidedFilter``);
5. scene radiance ``J = (I − A)/max(t, t0) + A`` with t0 = 0.1, clipped to [0, 1].

Assumptions (the prior's): haze-free outdoor patches have a dark pixel in some channel, and the haze is
one homogeneous medium lit by one airlight. Bright, greyish surfaces (white walls, sky, snow) break it:
their haze is over-estimated and they come out too dark. The papers' parameters are for images of about
600 x 400 px (patch 15 px, guided-filter radius 60 px, ε = 1e-4); here the patch and the radius are scaled
with the image width against ``reference_width_px`` (at least 3 px and 2 px) so that a 64-px-wide test
image and a 600-px photo see the same fraction of the view. Each view is restored on its own, with its
own airlight, as a per-view baseline does.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from metegs.config import InstantiateConfig
from metegs.errors import ConfigError
from metegs.restore.base import check_image


@dataclass
class DarkChannelPriorConfig(InstantiateConfig):
    """Dark channel prior dehazing with guided-filter refinement (He et al. 2009/2011)."""

    _target: type = field(default_factory=lambda: DarkChannelPrior, repr=False)
    patch_px: int = 15
    """Side of the patch Ω at the reference width (15 px in the paper)."""
    omega: float = 0.95
    """Fraction of the haze removed (0.95 in the paper)."""
    t0: float = 0.1
    """Lower bound of the transmission in the recovery (0.1 in the paper)."""
    top_fraction: float = 0.001
    """Fraction of brightest dark-channel pixels the airlight is taken from (0.1 % in the paper)."""
    gf_radius_px: int = 60
    """Guided-filter radius at the reference width (60 px in the guided-filter paper's dehazing example)."""
    gf_eps: float = 1e-4
    """Guided-filter regularisation ε (1e-4 in the guided-filter paper's dehazing example)."""
    reference_width_px: int = 600
    """Image width the patch and radius above are meant for; other widths scale them (0: no scaling)."""


def _scaled(value: int, width: int, reference: int, minimum: int) -> int:
    if reference <= 0:
        return max(minimum, int(value))
    return max(minimum, int(round(value * width / reference)))


def dark_channel(image: np.ndarray, patch: int) -> np.ndarray:
    """[H, W] min over channels and over a ``patch`` x ``patch`` square (an erosion) of [H, W, 3]."""
    kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (patch, patch))
    return cv2.erode(image.min(axis=2), kernel, borderType=cv2.BORDER_REPLICATE)


def estimate_airlight(image: np.ndarray, dark: np.ndarray, top_fraction: float = 0.001) -> np.ndarray:
    """[3] airlight: the brightest input pixel (R+G+B) among the ``top_fraction`` brightest dark-channel pixels."""
    flat_dark = dark.reshape(-1)
    n = max(1, int(round(top_fraction * flat_dark.size)))
    candidates = np.argpartition(flat_dark, flat_dark.size - n)[flat_dark.size - n :]
    pixels = image.reshape(-1, 3)[candidates]
    return pixels[int(np.argmax(pixels.sum(axis=1)))].astype(np.float32)


class DarkChannelPrior:
    """He et al.'s dehazing (see the module docstring)."""

    name = "dcp"
    removes = frozenset({"fog"})

    def __init__(self, config: DarkChannelPriorConfig | None = None):
        if not hasattr(cv2, "ximgproc"):  # before any photo is restored, not at the first guided filter
            raise ConfigError(
                f"the dcp restorer needs OpenCV's contrib module (cv2.ximgproc), which the OpenCV at {cv2.__file__} "
                f"({cv2.__version__}) lacks: another OpenCV package (opencv-python or opencv-python-headless) shadows "
                "metegs's opencv-contrib-python-headless; pip uninstall opencv-python opencv-python-headless, then "
                "pip install --force-reinstall opencv-contrib-python-headless"
            )
        self.config = config or DarkChannelPriorConfig()

    def transmission(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(refined transmission [H, W], airlight [3]) of one image [H, W, 3] in [0, 1]."""
        c = self.config
        width = image.shape[1]
        patch = _scaled(c.patch_px, width, c.reference_width_px, 3) | 1
        radius = _scaled(c.gf_radius_px, width, c.reference_width_px, 2)
        airlight = estimate_airlight(image, dark_channel(image, patch), c.top_fraction)
        normalised = image / np.maximum(airlight, 1e-3)[None, None, :]
        coarse = 1.0 - c.omega * dark_channel(normalised.astype(np.float32), patch)
        grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        refined = cv2.ximgproc.guidedFilter(grey, coarse.astype(np.float32), radius, c.gf_eps, -1)
        return np.clip(refined, 0.0, 1.0), airlight

    def restore(self, image: np.ndarray) -> np.ndarray:
        image = check_image(image, self.name)
        t, airlight = self.transmission(image)
        t = np.maximum(t, self.config.t0)[..., None]
        out = (image - airlight) / t + airlight
        return np.clip(out, 0.0, 1.0).astype(np.float32)
