"""Smoothing of a reference model's per-source images against their Monte Carlo noise: a
re-rendered candidate's change as a smoothed ratio (``smoothed_change``), and each LED's
leak image around the tube's axis (``axially_smoothed``)."""

from __future__ import annotations

import functools
import math

import numpy as np

#: A re-rendered candidate's change is taken as the identity's image times the ratio of
#: both images smoothed by a Gaussian of this many basis pixels (``smoothed_change``).
#: Its grid point and the identity follow different light paths, so their difference
#: carries both renders' Monte Carlo noise, which at 80x60 was larger than a medium's
#: change: a hidden scattering of 156 per m, predicted at its value, left a held-out MAE
#: of 0.0199 where the simulation with its exposure alone left 0.0134. Smoothed by 2
#: pixels as a ratio, 0.0114; the same smoothing of the difference blurred a strong
#: absorption's change (98 per m: 0.0149 before, 0.029 after; as a ratio, 0.0143).
SPREAD_SMOOTH_PX = 2.0
#: Each LED's leak image (a glow from the glass core) is smoothed by a Gaussian of
#: (along circles about the principal point, across them) basis pixels
#: (``axially_smoothed``). The leak fraction is a regression coefficient on that image,
#: and the image's own Monte Carlo noise shrank it (regression dilution): hidden leaks of
#: 0.3, 0.164 and 0.266 were fitted at 0.241, 0.116 and 0.208; smoothed by 2 pixels each
#: way, at 0.257, 0.137 and 0.221, and each alone closed more of the held-out gap (20 % to
#: 28 %, 8 % to 14 %, 17 % to 24 %). The core is a tube about the camera's axis, so the
#: glow changes slowly around that axis and fast along it, towards the tip (the image's
#: centre): on a hidden leak of 0.3 (12 taps, judged as now), 2 pixels each way left the
#: tip at a held-out MAE of 0.0042 (0.0010 between two renders of the same physics), the
#: leak's radial profile blurred; (4, 0.75) left 0.0017, and the masked MAE went from
#: 0.00466 to 0.00450 (best of a grid of fractions and exposures for each).
LEAK_SMOOTH_PX = (4.0, 0.75)


def smoothed_change(image: np.ndarray, base: np.ndarray) -> np.ndarray:
    """(h, w, S) the change from ``base`` to ``image`` (per-source images at the film):
    base (G image / G base - 1), G a Gaussian of SPREAD_SMOOTH_PX over the film (a
    normalised convolution: the change is smooth where the light is, and keeps the
    identity's own detail); the plain difference where the smoothed identity is dark."""
    from scipy import ndimage

    sigma = (SPREAD_SMOOTH_PX, SPREAD_SMOOTH_PX, 0)
    num = ndimage.gaussian_filter(image, sigma, mode="nearest")
    den = ndimage.gaussian_filter(base, sigma, mode="nearest")
    lit = den > np.float32(1e-6 * max(float(base.max()), 1e-12))
    return np.where(lit, base * (num / np.where(lit, den, 1.0) - 1.0), image - base).astype(np.float32)


def axially_smoothed(images: np.ndarray, centre: tuple[float, float], sigma: tuple[float, float]) -> np.ndarray:
    """(h, w, S) ``images`` smoothed by a Gaussian of sigma[0] pixels of arc along the
    circles about ``centre`` (x, y in pixels) and of sigma[1] pixels across them: resampled
    onto a polar grid (half a pixel apart in radius and, at the farthest corner, in arc;
    bilinear, 'nearest' outside), filtered (around each circle periodically, by its FFT),
    and resampled back."""
    from scipy import ndimage

    h, w = images.shape[:2]
    there, back, transfer, radial = _polar_grid(h, w, float(centre[0]), float(centre[1]), tuple(map(float, sigma)))
    out = np.empty(images.shape, np.float32)
    for s in range(images.shape[2]):
        polar = ndimage.map_coordinates(np.asarray(images[..., s], np.float64), there, order=1, mode="nearest")
        polar = np.fft.irfft(np.fft.rfft(polar, axis=1) * transfer, n=transfer.shape[1] * 2 - 2, axis=1)
        if radial > 0:
            polar = ndimage.gaussian_filter1d(polar, radial, axis=0, mode="nearest")
        out[..., s] = ndimage.map_coordinates(np.concatenate([polar, polar[:, :1]], axis=1), back, order=1,
                                              mode="nearest")
    return out


@functools.lru_cache(maxsize=8)
def _polar_grid(h: int, w: int, cx: float, cy: float, sigma: tuple[float, float]):
    """``axially_smoothed``'s sampling: the polar grid's (rows, columns) in the image, the
    image's in the grid, each circle's transfer function and the radial sigma in samples."""
    rmax = math.hypot(max(cx, w - 1 - cx), max(cy, h - 1 - cy)) + 1.0
    nr, nt = int(math.ceil(2 * rmax)), 2 * int(math.ceil(2 * math.pi * rmax))  # nt even: irfft's length
    r = (np.arange(nr) + 0.5) * rmax / nr
    t = np.arange(nt) * 2 * math.pi / nt
    there = np.stack([cy + r[:, None] * np.sin(t)[None], cx + r[:, None] * np.cos(t)[None]])
    v, u = np.mgrid[0:h, 0:w]
    back = np.stack([np.hypot(u - cx, v - cy) * nr / rmax - 0.5,
                     np.mod(np.arctan2(v - cy, u - cx), 2 * math.pi) * nt / (2 * math.pi)])
    angle = sigma[0] / np.maximum(r, 0.5) * nt / (2 * math.pi)  # sigma[0] px of arc, in angle samples
    transfer = np.exp(-2.0 * (math.pi * np.fft.rfftfreq(nt)[None] * angle[:, None]) ** 2)
    return there, back, transfer, sigma[1] * nr / rmax
