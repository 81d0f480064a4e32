"""Elastic smoothing of a contact depth map: the paper's model of the membrane, shared by both renderers."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from .spec import Elastic

#: Border handling of G; 'mirror' is OpenCV's default BORDER_REFLECT_101, which the
#: published implementation used.
BORDER_MODE = "mirror"


def smooth(delta: np.ndarray, elastic: Elastic) -> np.ndarray:
    """G * delta: the truncated Gaussian of the elastic model (55x55, sigma 5 px by default)."""
    return ndimage.gaussian_filter(
        delta, elastic.sigma_px, truncate=elastic.radius_px / elastic.sigma_px, mode=BORDER_MODE
    )


def deform(depth: np.ndarray, ref_depth: np.ndarray, elastic: Elastic) -> np.ndarray:
    """D_def = min(D, D_ref - G * (D_ref - D)).

    The rigid imprint D is spread by the Gaussian G as an elastic membrane would, and the
    min keeps the indenter's own surface where it reaches deeper than the spread.

    depth, ref_depth : (H, W) float, metres, planar z-depth.  Returns (H, W), same dtype.
    """
    return np.minimum(depth, ref_depth - smooth(ref_depth - depth, elastic))
