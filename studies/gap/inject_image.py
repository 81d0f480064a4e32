"""The gap benchmark's injector (``studies.gap.inject``): the image stages. Optics (the
camera moved and turned, a lens' distortion, its fall-off, defocus) and the sensor (its
response and noise), each with OpenCV's own resampling and filters, never the diagnosis'
models. Arrays in, arrays out.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from scenes.camera import Camera


#: lens_distortion: largest undistorted radius tabulated, in focal lengths.
DISTORTION_MAX_RADIUS = 3.0


def misalign(image: np.ndarray, shift_x_px: float, shift_y_px: float, rotation: float,
             centre: tuple[float, float]) -> np.ndarray:
    """The frame rotated by ``rotation`` rad (counter-clockwise as displayed) about ``centre``
    (u, v) px, then shifted by (shift_x_px, shift_y_px) px; black where nothing maps.

    image : (H, W, 3) float32.  Returns the same shape and dtype.
    """
    A = cv2.getRotationMatrix2D((float(centre[0]), float(centre[1])), math.degrees(rotation), 1.0)
    A[:, 2] += (shift_x_px, shift_y_px)
    h, w = image.shape[:2]
    return cv2.warpAffine(image, A, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def distortion_maps(camera: Camera, k1: float, k2: float) -> tuple[np.ndarray, np.ndarray]:
    """Where each pixel of the distorted image looks in the ideal (pinhole) one.

    A Brown-Conrady lens moves the ideal point at normalised radius r (about the
    principal point, in focal lengths) to r (1 + k1 r^2 + k2 r^4). cv2.projectPoints
    tabulates that along the monotone branch, and the table is inverted per pixel;
    pixels whose radius no ideal point reaches get -1 (black through cv2.remap).

    Returns map_x, map_y : (H, W) float32, px.
    """
    r = np.linspace(0.0, DISTORTION_MAX_RADIUS, 4096)
    K = np.array([[camera.f, 0, camera.cx], [0, camera.f, camera.cy], [0, 0, 1.0]])
    table, _ = cv2.projectPoints(np.stack([r, np.zeros_like(r), np.ones_like(r)], 1), np.zeros(3), np.zeros(3), K,
                                 np.array([k1, k2, 0.0, 0.0]))
    r_d = (table[:, 0, 0] - camera.cx) / camera.f
    rising = np.diff(r_d) > 0
    end = len(r) if rising.all() else int(np.argmin(rising)) + 1  # the fold, if any
    r, r_d = r[:end], r_d[:end]
    v, u = np.mgrid[0 : camera.height, 0 : camera.width].astype(np.float64)
    du, dv = (u - camera.cx) / camera.f, (v - camera.cy) / camera.f
    rho = np.hypot(du, dv)  # distorted radius of each pixel, focal lengths
    ideal = np.interp(rho, r_d, r, right=np.nan)
    scale = np.divide(ideal, rho, out=np.ones_like(rho), where=rho > 0)
    map_x = np.where(np.isfinite(ideal), camera.cx + camera.f * du * scale, -1.0).astype(np.float32)
    map_y = np.where(np.isfinite(ideal), camera.cy + camera.f * dv * scale, -1.0).astype(np.float32)
    return map_x, map_y


def distort(image: np.ndarray, camera: Camera, k1: float, k2: float) -> np.ndarray:
    """The image through a Brown-Conrady lens (k1, k2 radial); (H, W, 3) float32 in and out."""
    map_x, map_y = distortion_maps(camera, k1, k2)
    return cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def vignette(image: np.ndarray, centre: tuple[float, float], focal_px: float, exponent: float) -> np.ndarray:
    """Off-axis falloff V = cos(theta)^n, tan(theta) = r / f_v, r the distance to ``centre``.

    image : (H, W, 3) float; centre : (u, v) px, the optical centre; focal_px : f_v, px;
    exponent : n (4 for the natural cos^4 law, 0 for none).  Returns image * V, same dtype.
    """
    if not focal_px > 0:
        raise ValueError(f"focal_px must be > 0, got {focal_px}")
    h, w = image.shape[:2]
    v, u = np.mgrid[0:h, 0:w]
    theta = np.arctan(np.hypot(u - centre[0], v - centre[1]) / focal_px)
    return image * (np.cos(theta) ** exponent).astype(image.dtype)[..., None]


def blur(image: np.ndarray, sigma_px: float) -> np.ndarray:
    """The optics' point spread as a Gaussian of ``sigma_px`` px; same shape and dtype."""
    if not sigma_px > 0:
        raise ValueError(f"sigma_px must be > 0, got {sigma_px}")
    return cv2.GaussianBlur(image, (0, 0), sigma_px)


def respond(image: np.ndarray, gamma_enc: float, gains, crosstalk: np.ndarray) -> np.ndarray:
    """The camera's own response: out = clip(gains * (C @ in), 0, 1) ** (1 / gamma_enc).

    image : (H, W, 3) float in [0, 1]; gains : (3,) white balance; crosstalk : C (3, 3),
    rows summing to 1 (C[i, j] is how much of channel j leaks into channel i).
    Returns the same shape, image's dtype.
    """
    if not gamma_enc > 0:
        raise ValueError(f"gamma_enc must be > 0, got {gamma_enc}")
    mixed = image @ np.asarray(crosstalk, dtype=image.dtype).T * np.asarray(gains, dtype=image.dtype)
    return np.clip(mixed, 0, 1) ** image.dtype.type(1.0 / gamma_enc)


def add_noise(image: np.ndarray, a: float, b: float, rng: np.random.Generator) -> np.ndarray:
    """Signal-dependent Gaussian sensor noise of variance a I + b; same shape and dtype."""
    if not (a >= 0 and b >= 0):
        raise ValueError(f"noise a and b must be >= 0, got a={a}, b={b}")
    std = np.sqrt(a * np.maximum(image, 0) + b)
    return image + std * rng.standard_normal(image.shape, dtype=np.float32).astype(image.dtype, copy=False)
