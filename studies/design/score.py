"""How good a design's tactile images are: the contrast of a standard tap per unit depth,
how evenly it spreads over the membrane, and where it is lost in the camera's noise.

Arrays in, numbers out; the taps are rendered by ``studies.design.loop``.

* A tap's **contrast** is the 95th percentile (CONTRAST_PERCENTILE), over the pixels the
  tap changes at all, of the change's largest channel in units of the real camera's
  noise in that channel (``scenes.reference_data.CAMERA_NOISE_RGB``): a signal-to-noise
  ratio, so that a change in the dim blue channel counts as much as its noise allows.
  Divided by the tap's depth it is the contrast per unit depth, per millimetre in
  reports.
* A tap is **dead** when its contrast stays under VISIBLE_SNR: the LEDs' light does not
  reach it, or reaches it so evenly that the dent does not show above the noise.
* A design's **score** is the 10th percentile (SCORE_PERCENTILE) of its taps' contrast
  per unit depth: the contrast that nine taps in ten over the membrane reach. One number
  that falls when the contrast is low, when it is uneven, and when dead zones appear.
  The median, the evenness (10th over 90th percentile) and the share of dead taps are
  reported beside it.
"""

from __future__ import annotations

import numpy as np

from scenes.reference_data import CAMERA_NOISE_RGB

#: The percentile of a tap's changed pixels its contrast is read at.
CONTRAST_PERCENTILE = 95.0
#: A tap whose contrast is below this many noise standard deviations is dead.
VISIBLE_SNR = 3.0
#: The percentile over a design's taps that is its score.
SCORE_PERCENTILE = 10.0
#: Changes smaller than this (display units) are no change: the renderer's rounding.
CHANGE_EPS = 1e-6


def changed_pixels(no_contact: np.ndarray, frame: np.ndarray) -> np.ndarray:
    """(H, W) bool: where a frame differs from the no-contact frame in any channel."""
    if no_contact.shape != frame.shape or frame.ndim != 3 or frame.shape[-1] != 3:
        raise ValueError(f"no_contact and frame must both be (H, W, 3), got {no_contact.shape} and {frame.shape}")
    return (np.abs(frame - no_contact) > CHANGE_EPS).any(axis=-1)


def tap_contrast(no_contact: np.ndarray, frame: np.ndarray, pixels: np.ndarray | None = None,
                 noise=CAMERA_NOISE_RGB) -> float:
    """A tap's contrast in noise units: the CONTRAST_PERCENTILE over ``pixels`` (default:
    the changed ones) of max over channels of |frame - no_contact| / noise; 0 when the tap
    changes nothing.

    no_contact, frame : (H, W, 3) float.  noise : (3,) positive, the same units.
    """
    pixels = changed_pixels(no_contact, frame) if pixels is None else np.asarray(pixels, bool)
    noise = np.asarray(noise, dtype=np.float64)
    if noise.shape != (3,) or not (noise > 0).all():
        raise ValueError(f"noise must be 3 positive numbers (one per channel), got {noise!r}")
    if pixels.shape != frame.shape[:2]:
        raise ValueError(f"pixels must be {frame.shape[:2]}, got {pixels.shape}")
    if not pixels.any():
        return 0.0
    snr = (np.abs(frame[pixels] - no_contact[pixels]) / noise).max(axis=-1)
    return float(np.percentile(snr, CONTRAST_PERCENTILE))


def design_score(contrast: np.ndarray, depth_m: np.ndarray) -> dict:
    """A design's score from its taps' contrasts (N,) in noise units at depths (N,) metres.

    Returns score, median, p90 (per metre), evenness (p10 / p90, 0 when p90 is 0) and
    dead_share (contrast under VISIBLE_SNR).
    """
    contrast, depth_m = np.asarray(contrast, dtype=np.float64), np.asarray(depth_m, dtype=np.float64)
    if contrast.ndim != 1 or contrast.shape != depth_m.shape or len(contrast) == 0:
        raise ValueError(f"contrast and depth_m must be equal (N,) arrays, N >= 1, got {contrast.shape} and "
                         f"{depth_m.shape}")
    if not (np.isfinite(contrast).all() and (contrast >= 0).all()):
        raise ValueError("contrast must be finite and >= 0")
    if not (np.isfinite(depth_m).all() and (depth_m > 0).all()):
        raise ValueError("depth_m must be finite and > 0")
    per_m = contrast / depth_m
    p10, median, p90 = np.percentile(per_m, [SCORE_PERCENTILE, 50.0, 100.0 - SCORE_PERCENTILE])
    return {"score": float(p10), "median": float(median), "p90": float(p90),
            "evenness": float(p10 / p90) if p90 > 0 else 0.0,
            "dead_share": float(np.mean(contrast < VISIBLE_SNR))}
