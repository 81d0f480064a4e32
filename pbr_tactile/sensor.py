"""Sensor-side effects on a rendered image: vignetting, lens distortion, sensor noise."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from scenes.camera import Camera, undistortion_stretch

from .effects import Effects


def vignetting(image: np.ndarray, camera: Camera, strength: float) -> np.ndarray:
    """Multiply by 1 - strength (r / R)^2: 1 at the principal point, 1 - strength at the
    image circle's radius R, clipped at 0 beyond. image : (H, W, 3)."""
    if strength == 0:
        return image
    v, u = np.mgrid[0 : image.shape[0], 0 : image.shape[1]]
    scale = image.shape[0] / camera.height
    r2 = ((u - camera.cx * scale) ** 2 + (v - camera.cy * scale) ** 2) / (camera.mask_radius_px * scale) ** 2
    return image * np.clip(1.0 - strength * r2, 0.0, None)[..., None]


def distort(image: np.ndarray, camera: Camera, k1: float, k2: float) -> np.ndarray:
    """Resample a pinhole image as seen through a lens with radial distortion.

    A ray at normalised radius r_u lands at r_d = r_u (1 + k1 r_u^2 + k2 r_u^4) (Brown's
    model, coordinates divided by the focal length; ``scenes.camera.undistorted_radius``,
    the one convention of the reference and the diagnosis's catalogue): each output pixel
    is read at its undistorted position, bilinear; black where no ray lands.
    """
    if k1 == 0 and k2 == 0:
        return image
    h, w = image.shape[:2]
    scale = h / camera.height
    f, cx, cy = camera.f * scale, camera.cx * scale, camera.cy * scale
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    r_d = np.hypot(u - cx, v - cy) / f
    stretch = undistortion_stretch(r_d, k1, k2)
    coords = [np.nan_to_num(cy + (v - cy) * stretch, nan=-2.0), np.nan_to_num(cx + (u - cx) * stretch, nan=-2.0)]
    return np.stack([ndimage.map_coordinates(image[..., c], coords, order=1, mode="constant") for c in range(image.shape[2])],
                    axis=-1).astype(image.dtype)


def add_noise(image: np.ndarray, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """Additive Gaussian sensor noise of standard deviation sigma (image units)."""
    if sigma == 0:
        return image
    return image + rng.normal(0.0, sigma, image.shape).astype(image.dtype)


def apply(image: np.ndarray, camera: Camera, effects: Effects, rng: np.random.Generator) -> np.ndarray:
    """Lens distortion, then vignetting, then noise, as light meets the sensor."""
    out = distort(image, camera, *effects.lens_distortion)
    out = vignetting(out, camera, effects.vignetting)
    return add_noise(out, effects.sensor_noise, rng)
