"""Backgrounds of the fast path: none, a solid colour, or a real no-contact image."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from scenes.camera import Camera
from scenes.images import read_rgb


def make_background(kind: str | Path, camera: Camera, colour=(0.6, 0.5, 0.96)) -> np.ndarray:
    """The background B of I = k_a i_a B + sum_m I_m.

    kind : "none" (zeros), "solid" (``colour``, linear RGB in [0, 1]), or the path of a
        real no-contact image of exactly the camera's size.

    Returns (H, W, 3) float32 linear RGB.
    """
    if isinstance(kind, str) and kind == "none":
        return np.zeros(camera.shape + (3,), np.float32)
    if isinstance(kind, str) and kind == "solid":
        colour = np.asarray(colour, dtype=np.float32)
        if colour.shape != (3,) or not np.all((colour >= 0) & (colour <= 1)):
            raise ValueError(f"solid background colour must be 3 values in [0, 1], got {colour}")
        return np.broadcast_to(colour, camera.shape + (3,)).copy()
    return check_background(read_rgb(kind, camera.shape), camera)


def check_background(image: np.ndarray, camera: Camera, name: str = "background") -> np.ndarray:
    """Validate a background image: (H, W, 3) float in [0, 1] of the camera's size."""
    image = np.asarray(image)
    if image.shape != camera.shape + (3,) or image.dtype.kind != "f":
        raise ValueError(
            f"{name} must be {camera.shape + (3,)} float RGB in [0, 1], got {image.shape} {image.dtype}"
        )
    if not np.all(np.isfinite(image)) or image.min() < 0 or image.max() > 1:
        raise ValueError(f"{name} values must be finite and in [0, 1]")
    return image.astype(np.float32, copy=False)
