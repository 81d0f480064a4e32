"""A real sensor image as the calibration sees it: checked, its lit circle, its sectors,
its clipped pixels, and how well a prediction explains it on held-out pixels (R^2 of
``scenes.image_stats``, with its interval over resampled held-out sectors)."""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from scenes.camera import Camera
from scenes.image_stats import percentile_interval, r2

#: Angular sectors of the image circle: even ones fit, odd ones judge.
SECTORS = 12
#: A real pixel at or above this (in [0, 1]) in a channel is clipped there.
CLIP_LEVEL = 254.0 / 255.0
#: A channel clipped over more than this share of the image circle is "saturated": it
#: is censored in the fit and not judged.
SATURATED_SHARE = 0.5
#: Pixels above this in any channel are inside the real image circle.
CIRCLE_THRESHOLD = 8.0 / 255.0


def check_real(image: np.ndarray, camera: Camera, name: str = "image") -> np.ndarray:
    """A real (H, W, 3) image in [0, 1] at the camera's size, checked: not blank, not
    saturated almost everywhere."""
    image = np.asarray(image)
    if image.shape != (camera.height, camera.width, 3):
        raise ValueError(f"{name} must be {camera.width}x{camera.height} RGB (the spec's camera), got shape "
                         f"{image.shape}")
    image = image.astype(np.float64)
    if not np.all(np.isfinite(image)) or image.min() < 0 or image.max() > 1:
        raise ValueError(f"{name} must hold finite values in [0, 1]")
    lit = image.max(axis=2) > CIRCLE_THRESHOLD
    if lit.mean() < 0.05:
        raise ValueError(f"{name} is blank: {lit.mean():.1%} of its pixels are above {CIRCLE_THRESHOLD:.3f}")
    clipped = (image >= CLIP_LEVEL).all(axis=2)[lit].mean()
    if clipped > 0.9:
        raise ValueError(f"{name} is saturated almost everywhere: {clipped:.0%} of its lit pixels are clipped in "
                         "every channel; lower the exposure")
    return image


def image_circle(image: np.ndarray) -> tuple[float, float, float] | None:
    """(cx, cy, radius) px of the lit disc of a real image, or None where the optics
    fill the frame (the lit area is more than 98 % of it)."""
    lit = np.asarray(image).max(axis=2) > CIRCLE_THRESHOLD
    lit = ndimage.binary_opening(lit, iterations=2)
    if lit.mean() > 0.98:
        return None
    v, u = np.nonzero(lit)
    return float(u.mean()), float(v.mean()), float(math.sqrt(lit.sum() / math.pi))


def sector_index(shape: tuple[int, int], centre: tuple[float, float], sectors: int = SECTORS) -> np.ndarray:
    """(H, W) int: the angular sector of each pixel about ``centre`` (u, v)."""
    v, u = np.mgrid[0:shape[0], 0:shape[1]]
    angle = np.mod(np.arctan2(v - centre[1], u - centre[0]), 2 * math.pi)
    return np.minimum((angle / (2 * math.pi) * sectors).astype(int), sectors - 1)


def film_sectors(camera: Camera, circle: tuple[float, float, float] | None, film: tuple[int, int]) -> np.ndarray:
    """(h, w) int: ``sector_index`` at a film of ``film`` (w, h) px about the image
    circle's centre (``circle``, at the camera's size; None: the principal point), moved
    to the film's pixels."""
    width, height = film
    s = height / camera.height
    centre = (camera.cx, camera.cy) if circle is None else circle[:2]
    return sector_index((height, width), ((centre[0] + 0.5) * s - 0.5, (centre[1] + 0.5) * s - 0.5))


def film_factor(shape: tuple[int, ...], film: tuple[int, int]) -> int:
    """The whole factor k between an (H, W, ...) camera image and the film (w, h)."""
    H, W = shape[:2]
    k = H // film[1]
    if k < 1 or k * film[1] != H or k * film[0] != W:
        raise ValueError(f"the film {film[0]}x{film[1]} must divide the camera's {W}x{H} evenly")
    return k


def heldout_interval(pred: np.ndarray, real: np.ndarray, pixels: np.ndarray, sector: np.ndarray, seed: int = 0,
                     count: int = 1000) -> list[float]:
    """5-95 % bootstrap interval of the held-out R^2 over the held-out sectors (drawn
    with replacement, each sector's pixels weighted by how often it was drawn)."""
    rng = np.random.default_rng(seed)
    odd = np.arange(1, SECTORS, 2)
    values = [r2(pred, real, pixels, np.bincount(rng.choice(odd, len(odd)), minlength=SECTORS)[sector])
              for _ in range(count)]
    # NaN: every drawn sector is empty here (a clipped channel), or flat
    values = [v for v in values if not math.isnan(v)]
    return percentile_interval(values) if values else [float("nan")] * 2
