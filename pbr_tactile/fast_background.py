"""The fast path's background term fitted to a real no-contact image
(``scenes.background_model``) and judged like the reference's calibration."""

from __future__ import annotations

import numpy as np

from scenes.camera import Camera
from scenes.image_stats import r2

from .real_image import heldout_interval

def fit_fast_background(r, circle, camera: Camera, train, test, clipped, judged: dict, sector, seed: int):
    """The fast path's background term fitted on the training sectors
    (scenes.background_model) and judged like the reference; with the best solid colour
    (each channel's training mean) for comparison. Returns the profile table and the
    report's ``fast_path`` section (with the film-sized ``image``, popped by the caller)."""
    from scenes import background_model

    full = (camera.height, camera.width)
    table = background_model.fit(r, circle, train, full, clipped)
    image = background_model.evaluate(table, circle, r.shape[:2], full).astype(np.float64)
    solid = np.where(test[..., None], [r[..., c][train].mean() for c in range(3)], 0.0)
    channels = list(enumerate("rgb"))
    section = {
        "background_model": (f"{background_model.MODEL}: Legendre polynomials of the image circle's radius to degree "
                              f"{table['radial_degree']} times azimuthal harmonics to {table['harmonics']}, "
                              "least squares per channel on the training sectors, clipped pixels censored"),
        "heldout_r2": {ch: r2(image[..., c], r[..., c], judged[ch]) for c, ch in channels},
        "heldout_r2_interval": {ch: heldout_interval(image[..., c], r[..., c], judged[ch], sector, seed)
                                for c, ch in channels},
        "heldout_mae": {ch: float(np.abs(image[..., c] - r[..., c])[judged[ch]].mean()) for c, ch in channels},
        "solid": {"heldout_r2": {ch: r2(solid[..., c], r[..., c], judged[ch]) for c, ch in channels},
                  "heldout_mae": {ch: float(np.abs(solid[..., c] - r[..., c])[judged[ch]].mean())
                                  for c, ch in channels}},
        "image": image,
    }
    return {**table, "coefficients": table["coefficients"].tolist()}, section
