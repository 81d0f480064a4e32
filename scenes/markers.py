"""Printed marker dots on a membrane: found in each frame and filled from around them.

Many units (the GelSight Mini's marker gel, DIGITs with printed dots, most units built for
slip and shear) carry a grid of dark dots on their membrane. Neither renderer draws them,
so a set of such presses is compared with its dots taken out: ``tactile-sim import
--markers inpaint``.

- A dot is darker than its surroundings and smaller than ``dot_m``: it is where the
  image's black top-hat (``skimage.morphology.black_tophat``: the grey closing with a disc
  ``dot_m`` across, less the image; Soille, "Morphological Image Analysis", 2003) exceeds
  ``contrast`` in the mean over channels. A press's own change is smooth over several
  dots' widths and does not register; a dot's edge is caught by growing the mask
  ``GROW_PX``.
- Each frame's dots are found in that frame, so a dot that moves under a press is
  masked where it went, and the frame is filled over its mask by biharmonic inpainting
  (``skimage.restoration.inpaint_biharmonic``; Damelin and Hoang, 2018).

That this leaves a calibration and a comparison as they would be without dots is measured,
on the public presses with dots drawn on them that move under each press, by
``studies.markers`` (``docs/your-sensor.md``).
"""

from __future__ import annotations

import numpy as np

#: The largest dot, metres (an estimate: published marker gels print dots 0.3 to 0.8 mm
#: across; the closing's disc must be wider than a dot and narrower than a press).
DOT_M = 1.0e-3
#: How much darker than its surroundings (mean over channels, [0, 1]) a pixel must be to
#: count as a dot's.
CONTRAST = 0.04
#: Pixels the mask is grown by, to take in a dot's soft edge.
GROW_PX = 1


def marker_mask(image: np.ndarray, dot_px: float, contrast: float = CONTRAST) -> np.ndarray:
    """(H, W) bool: the pixels of ``image`` (H, W, 3) in [0, 1] on a dark dot narrower than
    ``dot_px`` pixels (module doc)."""
    from skimage.morphology import black_tophat, dilation, disk

    image = np.asarray(image, np.float64)
    if image.ndim != 3 or image.shape[-1] != 3:
        raise ValueError(f"image must be (H, W, 3), got {image.shape}")
    if not (np.isfinite(dot_px) and dot_px >= 1):
        raise ValueError(f"a dot's size must be at least a pixel, got {dot_px!r} px")
    radius = max(1, int(np.ceil(dot_px / 2)))
    found = black_tophat(image.mean(axis=2), disk(radius)) > contrast
    return dilation(found, disk(GROW_PX)) if GROW_PX else found


def inpaint(image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """``image`` (H, W, 3) filled over ``mask`` (H, W) from around it (module doc)."""
    from skimage.restoration import inpaint_biharmonic

    if not mask.any():
        return np.asarray(image, np.float64)
    return np.clip(inpaint_biharmonic(np.asarray(image, np.float64), mask, channel_axis=-1), 0.0, 1.0)


def remove_markers(no_contact: np.ndarray, frames: np.ndarray, pixel_m: float, dot_m: float = DOT_M,
                   contrast: float = CONTRAST) -> tuple[np.ndarray, np.ndarray, dict]:
    """(the no-contact frame, the frames, a report) with each frame's dots found and
    filled (module doc); the report gives the dots' share of the no-contact frame and the
    median share of the presses' frames masked."""
    dot_px = dot_m / pixel_m
    f0_mask = marker_mask(no_contact, dot_px, contrast)
    clean_f0 = inpaint(no_contact, f0_mask)
    clean = np.empty_like(np.asarray(frames, np.float64))
    shares = []
    for i, frame in enumerate(frames):
        mask = marker_mask(frame, dot_px, contrast)
        clean[i] = inpaint(frame, mask)
        shares.append(float(mask.mean()))
    return clean_f0, clean, {"method": "black top-hat, biharmonic inpainting (scenes.markers)",
                             "dot_mm": dot_m * 1e3, "contrast": contrast,
                             "no_contact_share": float(f0_mask.mean()),
                             "frame_share_median": float(np.median(shares)) if shares else 0.0}
