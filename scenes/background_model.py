"""A smooth model of a sensor's no-contact image: the fast path's calibrated background.

The fast path renders I = k_a i_a B + sum_m I_m, and with the published tangent light
fields the LED terms vanish without contact, so its no-contact image is the background
term alone. Calibration fits B to a real no-contact image as a smooth function of the
image circle's polar coordinates (r over the circle's radius, azimuth theta):

    B_c(r, theta) = sum_{k, j} a_ckj P_j(2 r - 1) h_k(theta)

with P_j the Legendre polynomials up to RADIAL_DEGREE and h_k the harmonics 1, cos(k
theta), sin(k theta) up to HARMONICS (the issue's measured smooth model: 3 harmonics and
8th order in radius explain 0.94 of the held-out variance of red and green). The
coefficients are plain data in a profile's ``phong.background`` table, so the fast path
can render the calibrated unit's background at any resolution without its image.
"""

from __future__ import annotations

import numpy as np

from .profile import circle_polar

#: Azimuthal harmonics and radial (Legendre) degree of the model.
HARMONICS = 3
RADIAL_DEGREE = 8
#: Refits of the censored least squares (``fit``) at most.
CENSORED_ITERATIONS = 8
#: The name of this model in a profile's ``phong.background.model``.
MODEL = "polar_legendre_harmonics"


def design(r: np.ndarray, theta: np.ndarray, harmonics: int = HARMONICS, degree: int = RADIAL_DEGREE) -> np.ndarray:
    """(..., K) the model's basis at radii ``r`` (over the circle's) and azimuths ``theta``."""
    radial = np.polynomial.legendre.legvander(2.0 * np.clip(r, 0.0, 1.0) - 1.0, degree)
    angular = [np.ones_like(theta)]
    for k in range(1, harmonics + 1):
        angular += [np.cos(k * theta), np.sin(k * theta)]
    angular = np.stack(angular, axis=-1)
    return (radial[..., :, None] * angular[..., None, :]).reshape(r.shape + (-1,))


def fit(image: np.ndarray, circle: tuple[float, float, float], pixels: np.ndarray,
        full_shape: tuple[int, int] | None = None, clipped: np.ndarray | None = None,
        harmonics: int = HARMONICS, degree: int = RADIAL_DEGREE) -> dict:
    """Least-squares coefficients of each channel of ``image`` (h, w, 3) on ``pixels``
    (h, w) bool, with ``clipped`` (h, w, 3) bool pixels censored: a clipped pixel says only
    that the truth is at least its value, so it costs nothing where the model predicts
    more (fitted on every pixel first, then refitted without the clipped pixels predicted
    above their value, until that set stops changing).
    ``circle`` (cx, cy, radius) is in pixels of ``full_shape`` (default: the image's).
    Returns the profile table (``model``, ``harmonics``, ``radial_degree``,
    ``coefficients`` (3, K))."""
    image = np.asarray(image, np.float64)
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"the background image must be (H, W, 3), got {image.shape}")
    pixels = np.asarray(pixels, bool)
    r, theta = circle_polar(circle, image.shape[:2], full_shape or image.shape[:2])
    X = design(r, theta, harmonics, degree)
    if pixels.sum() < X.shape[-1]:
        raise ValueError(f"a background model of {X.shape[-1]} terms needs at least as many pixels, got {pixels.sum()}")
    rows = []
    for c in range(3):
        y, use = image[..., c], pixels
        for _ in range(CENSORED_ITERATIONS):
            coef = np.linalg.lstsq(X[use], y[use], rcond=None)[0]
            if clipped is None:
                break
            new = pixels & ~(clipped[..., c] & (X @ coef >= y))
            if np.array_equal(new, use) or new.sum() < X.shape[-1]:
                break
            use = new
        rows.append(coef)
    return {"model": MODEL, "harmonics": harmonics, "radial_degree": degree, "coefficients": np.stack(rows)}


def evaluate(table: dict, circle: tuple[float, float, float], shape: tuple[int, int],
             full_shape: tuple[int, int]) -> np.ndarray:
    """(h, w, 3) float32 in [0, 1]: the background of a profile's ``phong.background``
    ``table`` at ``shape``, 0 outside the image circle (cx, cy, radius in pixels of
    ``full_shape``)."""
    try:
        model, harmonics, degree = table["model"], int(table["harmonics"]), int(table["radial_degree"])
        coefficients = np.asarray(table["coefficients"], np.float64)
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"profile phong.background is malformed ({exc!r}); expected model, harmonics, "
                         "radial_degree, coefficients") from None
    if model != MODEL:
        raise ValueError(f"profile phong.background.model must be {MODEL!r}, got {model!r}")
    terms = (degree + 1) * (2 * harmonics + 1)
    if coefficients.shape != (3, terms) or not np.all(np.isfinite(coefficients)):
        raise ValueError(f"profile phong.background.coefficients must be 3 rows of {terms} finite numbers, got shape "
                         f"{coefficients.shape}")
    r, theta = circle_polar(circle, shape, full_shape)
    out = design(r, theta, harmonics, degree) @ coefficients.T
    return np.where((r <= 1.0)[..., None], np.clip(out, 0.0, 1.0), 0.0).astype(np.float32)
