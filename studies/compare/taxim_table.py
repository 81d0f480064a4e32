"""Taxim's table refitted on a capture's own presses (``studies.compare.taxim`` renders
with it through the pip port), and the checks of the arrays both modules take.

The table (:func:`fit_polytable`, Taxim's ``Calibration/polyTableCalib.py``):
the background ``B`` is the no-contact frame blurred (σ = 50 px) and mixed
(:func:`background`); the target is the signed change ``ΔI = frame - B``; each pixel
inside the annotated circle, clipped to the ball's radius, takes the ball's normal
(θ = arcsin(r/R), φ = atan2(-dy, -dx)); per bin and channel, ΔI ≈ w·[x², y², xy, x, y, 1]
with (x, y) the pixel's column and row, which is where the port's renderer evaluates the
polynomial for a calibration written at the frames' size; bins no press saw take their
nearest fitted bin's coefficients, as Taxim fills them.

Two deviations from Taxim, each because the port renders what we fit:

- *All pixels of a bin*: Taxim keeps one pixel per bin per press (``map[idx] += value``
  with repeated indices: numpy's buffered fancy indexing keeps the last write) and fills
  each press's empty bins before fitting. We fit each bin on every pixel of every
  training press that falls in it (a bin needs :data:`MIN_PRESSES` presses to count as
  fitted), so no observation is thrown away and nothing depends on numpy's write order;
  empty bins are filled afterwards from the nearest fitted bin, which is what Taxim's
  per-press nearest-neighbour fill amounts to when every press sees the same bins.
- *The port's background*: Taxim keeps the blurred frame where the frame is 5 grey levels
  or more darker than its blur (dust), and mixes 15 % blur into the frame elsewhere. The
  port compares a [0, 1] image with 5 and so mixes everywhere. The fit's target must be
  the change from the background the renderer adds back, so we fit against the port's
  (on the Taxim set's frame the two rules differ at a fifth of the pixels, by up to 0.16).
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

#: Share of the blurred frame mixed into the background (Taxim's and the port's 0.15).
BACKGROUND_MIXING = 0.15
#: The port truncates its Gaussian kernels where a tap's weight falls below this share
#: of a unit-area kernel's peak; matching it makes our background the port's to 1e-7.
KERNEL_EPS = 1e-5
#: Bins per axis (slope, direction) of the Taxim set's 160x120 table (``polycalib_small``).
BINS = 80
#: Presses a bin must be seen in for its quadratic in position to count as fitted: six
#: unknowns, and one press alone spans a few pixels, not the frame.
MIN_PRESSES = 6
#: Singular values below this share of the largest leave a bin's fit rank-deficient.
RCOND = 1e-10
#: The polynomial's features, in the order of Taxim's table.
FEATURES = ("x^2", "y^2", "xy", "x", "y", "1")
#: Taxim's background blur (``kscale``), pixels of the frames it is fitted on.
BACKGROUND_SIGMA_PX = 50.0


def checked_image(name: str, value, shape: tuple[int, ...] | None = None) -> np.ndarray:
    """An RGB float image (or stack) in [0, 1]; ValueError naming ``name`` otherwise."""
    a = np.asarray(value)
    want = "(H, W, 3)" if shape is None else f"{shape}"
    if a.dtype.kind != "f" or a.shape[-1:] != (3,) or (shape is not None and a.shape != shape):
        raise ValueError(f"{name} must be {want} float RGB in [0, 1], got {a.shape} {a.dtype}")
    if not np.all(np.isfinite(a)) or a.min() < 0 or a.max() > 1:
        raise ValueError(f"{name} must hold finite values in [0, 1], got range "
                         f"[{np.nanmin(a):.3g}, {np.nanmax(a):.3g}]")
    return a.astype(np.float64)


def checked_positive(name: str, value) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a positive number, got {value!r}") from None
    if not math.isfinite(v) or v <= 0:
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    return v


def checked_size(name: str, value, least: int = 1) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < least:
        raise ValueError(f"{name} must be an integer >= {least}, got {value!r}")
    return int(value)


def checked_shape(value) -> tuple[int, int]:
    try:
        h, w = (int(s) for s in value)
    except (TypeError, ValueError):
        raise ValueError(f"shape must be (H, W), got {value!r}") from None
    if h < 3 or w < 3 or (h, w) != tuple(value):
        raise ValueError(f"shape must be (H, W) integers >= 3, got {value!r}")
    return h, w


def checked_point(name: str, value) -> np.ndarray:
    """(2,) finite (x = column, y = row) pixels; ValueError naming ``name`` otherwise."""
    a = np.asarray(value)
    if a.shape != (2,) or a.dtype.kind not in "iuf" or not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be (2,) finite (x = column, y = row) pixels, got {a.shape} {a.dtype}")
    return a.astype(np.float64)


def checked_centres(value, n: int | None = None) -> np.ndarray:
    c = np.asarray(value, dtype=np.float64) if np.asarray(value).dtype.kind in "iuf" else None
    if c is None or c.ndim != 2 or c.shape[1] != 2 or (n is not None and len(c) != n) or not np.all(np.isfinite(c)):
        got = np.asarray(value).shape
        raise ValueError(f"centres_px must be ({'N' if n is None else n}, 2) finite (x = column, y = row) "
                         f"pixels, got {got}")
    return c


# ----------------------------------------------------------------------------- the table

def _kernel_radius(sigma_px: float) -> int:
    """The port's Gaussian kernel half-width for σ (its size rule, :data:`KERNEL_EPS`)."""
    size = int(np.round(np.sqrt(-2 * np.log(KERNEL_EPS * np.sqrt(2 * np.pi) * sigma_px)) * sigma_px)) // 2 * 2 + 1
    return max((size - 1) // 2, 1)


def blurred(image: np.ndarray, sigma_rows: float, sigma_cols: float) -> np.ndarray:
    """Gaussian blur of each channel as the port blurs (mirror edges, its kernel size)."""
    return np.stack([ndimage.gaussian_filter(image[..., c], (sigma_rows, sigma_cols), mode="mirror",
                                             radius=(_kernel_radius(sigma_rows), _kernel_radius(sigma_cols)))
                     for c in range(image.shape[-1])], axis=-1)


def background(no_contact: np.ndarray, sigma_px: float = BACKGROUND_SIGMA_PX) -> np.ndarray:
    """The background Taxim's port adds to the table's change: B = 0.15 G_σ * f0 + 0.85 f0.

    Parameters
    ----------
    no_contact : (H, W, 3) float, RGB in [0, 1], the frame without contact (f0).
    sigma_px : the blur's σ, pixels of ``no_contact`` (Taxim: 50).

    Returns
    -------
    (H, W, 3) float64, RGB in [0, 1].

    Notes
    -----
    Taxim itself keeps the blurred frame where f0 is darker than its blur by 5 grey
    levels or more; the port mixes everywhere (module doc). We follow the port, which
    renders the table.
    """
    f0 = checked_image("no_contact", no_contact)
    sigma_px = checked_positive("sigma_px", sigma_px)
    return BACKGROUND_MIXING * blurred(f0, sigma_px, sigma_px) + (1 - BACKGROUND_MIXING) * f0


def press_angles(centre_px, radius_px: float, ball_radius_px: float,
                 shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The normals a ball's sphere gives the pixels of its press (Taxim's fit, step 3).

    Parameters
    ----------
    centre_px : (2,) float, the press's centre (x = column, y = row), pixels.
    radius_px : the press's annotated radius, pixels; clipped to ``ball_radius_px``.
    ball_radius_px : the ball's radius, pixels.
    shape : (H, W) of the frame.

    Returns
    -------
    theta : (H, W) float64, radians, the slope arcsin(r / R) (0 outside the press).
    phi : (H, W) float64, radians in [-π, π], the direction atan2(-dy, -dx), which is
        the port's atan2(∂z/∂row, ∂z/∂column) of the sphere as a height z toward the camera.
    inside : (H, W) bool, r² < min(radius_px², ball_radius_px²).
    """
    h, w = checked_shape(shape)
    centre = checked_point("centre_px", centre_px)
    radius_px = checked_positive("radius_px", radius_px)
    ball_radius_px = checked_positive("ball_radius_px", ball_radius_px)
    rows, cols = np.mgrid[:h, :w].astype(np.float64)
    dx, dy = cols - centre[0], rows - centre[1]
    r2 = dx * dx + dy * dy
    inside = r2 < min(radius_px, ball_radius_px) ** 2
    theta = np.where(inside, np.arcsin(np.sqrt(np.minimum(r2, ball_radius_px ** 2)) / ball_radius_px), 0.0)
    phi = np.where(inside, np.arctan2(-dy, -dx), 0.0)
    return theta, phi, inside


def bin_indices(theta: np.ndarray, phi: np.ndarray, bins: int) -> tuple[np.ndarray, np.ndarray]:
    """The table's bin of each normal, as the port's renderer discretises it.

    theta : (...) radians in [0, π/2]; phi : (...) radians in [-π, π]; bins : per axis.
    Returns (i_theta, i_phi), (...) int, each clamped to [0, bins - 1] as JAX's indexing
    clamps (θ = π/2 and φ = π fall in the last bin).
    """
    bins = checked_size("bins", bins, 2)
    step_theta = 0.5 * np.pi / (bins - 1)
    step_phi = 2 * np.pi / (bins - 1)
    i_theta = np.floor(np.asarray(theta) / step_theta).astype(np.int64)
    i_phi = np.floor((np.asarray(phi) + np.pi) / step_phi).astype(np.int64)
    return np.clip(i_theta, 0, bins - 1), np.clip(i_phi, 0, bins - 1)


def _features(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """(..., 6): [x², y², xy, x, y, 1] (:data:`FEATURES`)."""
    return np.stack([x * x, y * y, x * y, x, y, np.ones_like(x)], axis=-1)


def lookup(coeffs: np.ndarray, theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """The colour change a table gives each pixel (the port's rendering, step 7).

    Parameters
    ----------
    coeffs : (B, B, 3, 6) float, RGB change per (slope bin, direction bin, channel), [0, 1]
        units, on :data:`FEATURES` of the pixel's (column, row).
    theta, phi : (H, W) radians, each pixel's normal (:func:`press_angles`).

    Returns
    -------
    (H, W, 3) float64, the signed change ΔI in [0, 1] units.
    """
    coeffs = np.asarray(coeffs, dtype=np.float64)
    if coeffs.ndim != 4 or coeffs.shape[0] != coeffs.shape[1] or coeffs.shape[2:] != (3, 6):
        raise ValueError(f"coeffs must be (B, B, 3, 6) float, got {coeffs.shape}")
    theta, phi = np.asarray(theta), np.asarray(phi)
    if theta.ndim != 2 or theta.shape != phi.shape:
        raise ValueError(f"theta and phi must be the same (H, W), got {theta.shape} and {phi.shape}")
    i_theta, i_phi = bin_indices(theta, phi, coeffs.shape[0])
    rows, cols = np.mgrid[:theta.shape[0], :theta.shape[1]].astype(np.float64)
    return np.einsum("hwcf,hwf->hwc", coeffs[i_theta, i_phi], _features(cols, rows))


def _nearest_fill(coeffs: np.ndarray, fitted: np.ndarray) -> np.ndarray:
    """Each unfitted bin takes its nearest fitted bin's coefficients (index distance)."""
    _, (it, ip) = ndimage.distance_transform_edt(~fitted, return_indices=True)
    return coeffs[it, ip]


def fit_polytable(no_contact: np.ndarray, frames: np.ndarray, centres_px, radii_px, pixel_m: float,
                  ball_radius_m: float, bins: int = BINS, sigma_px: float = BACKGROUND_SIGMA_PX) -> dict:
    """Fit Taxim's polynomial lookup table from ball presses (module doc).

    Parameters
    ----------
    no_contact : (H, W, 3) float, RGB in [0, 1], the frame without contact.
    frames : (N, H, W, 3) float, RGB in [0, 1], one press each (the training presses).
    centres_px : (N, 2) float, each press's centre (x = column, y = row), pixels.
    radii_px : (N,) float, each press's annotated contact radius, pixels.
    pixel_m : a pixel's size on the gel, metres.
    ball_radius_m : the ball's radius, metres.
    bins : bins per axis (slope θ over [0, π/2], direction φ over [-π, π]).
    sigma_px : the background's blur, pixels (:func:`background`).

    Returns
    -------
    dict with
        ``coeffs`` (bins, bins, 3, 6) float64: per bin and RGB channel, the weights of
        :data:`FEATURES` of the pixel's (column, row), giving ΔI in [0, 1] units;
        ``fitted`` (bins, bins) bool: bins fitted from presses (the rest are filled);
        ``presses`` (bins, bins) int: how many presses saw each bin;
        ``samples`` (bins, bins) int: how many pixels each bin was fitted on;
        ``background`` (H, W, 3) float64: B, the change's reference;
        ``bins``, ``sigma_px``, ``pixel_m``, ``ball_radius_m``, ``shape`` (H, W).

    Notes
    -----
    Centres are used as given (Taxim truncates them to whole pixels: ``int(center)``).
    Each bin is fitted on all its pixels (module doc); it is fitted only from ``frames``.
    """
    f0 = checked_image("no_contact", no_contact)
    frames = np.asarray(frames)
    if frames.ndim != 4:
        raise ValueError(f"frames must be (N, H, W, 3) float RGB in [0, 1], got {frames.shape} {frames.dtype}")
    frames = checked_image("frames", frames, (len(frames),) + f0.shape)
    n = len(frames)
    centres = checked_centres(centres_px, n)
    radii = np.asarray(radii_px, dtype=np.float64) if np.asarray(radii_px).dtype.kind in "iuf" else None
    if radii is None or radii.shape != (n,) or not np.all(np.isfinite(radii)) or np.any(radii <= 0):
        raise ValueError(f"radii_px must be ({n},) positive pixels, got {np.asarray(radii_px).shape} "
                         f"{np.asarray(radii_px).dtype}")
    pixel_m = checked_positive("pixel_m", pixel_m)
    ball_radius_m = checked_positive("ball_radius_m", ball_radius_m)
    bins = checked_size("bins", bins, 2)
    h, w = f0.shape[:2]
    bg = background(f0, sigma_px)
    ball_px = ball_radius_m / pixel_m

    # Every in-circle pixel of every press: its bin, position, press and change.
    rows, cols = np.mgrid[:h, :w].astype(np.float64)
    index, xs, ys, press, change = [], [], [], [], []
    for i in range(n):
        theta, phi, inside = press_angles(centres[i], radii[i], ball_px, (h, w))
        i_theta, i_phi = bin_indices(theta[inside], phi[inside], bins)
        index.append(i_theta * bins + i_phi)
        xs.append(cols[inside])
        ys.append(rows[inside])
        press.append(np.full(inside.sum(), i))
        change.append(frames[i][inside] - bg[inside])
    index, xs, ys, press, change = (np.concatenate(a) for a in (index, xs, ys, press, change))
    if len(index) == 0:
        raise ValueError("no press has a pixel inside its circle: check centres_px, radii_px and the frames' size")

    order = np.argsort(index, kind="stable")
    index, xs, ys, press, change = index[order], xs[order], ys[order], press[order], change[order]
    # Scaled positions keep the normal matrix well conditioned; weights are scaled back.
    scale = np.array([1 / w ** 2, 1 / h ** 2, 1 / (w * h), 1 / w, 1 / h, 1.0])
    design = _features(xs / w, ys / h)
    coeffs = np.zeros((bins * bins, 3, 6))
    fitted = np.zeros(bins * bins, bool)
    presses = np.zeros(bins * bins, np.int64)
    samples = np.bincount(index, minlength=bins * bins)
    starts = np.flatnonzero(np.r_[True, index[1:] != index[:-1]])
    for start, stop in zip(starts, np.r_[starts[1:], len(index)]):
        b = index[start]
        presses[b] = len(np.unique(press[start:stop]))
        if presses[b] < MIN_PRESSES:
            continue
        weights, _, rank, _ = np.linalg.lstsq(design[start:stop], change[start:stop], rcond=RCOND)
        if rank < 6:
            continue
        coeffs[b] = (weights * scale[:, None]).T
        fitted[b] = True
    if not fitted.any():
        raise ValueError(f"no bin was seen by {MIN_PRESSES} presses: fit on more presses (got {n}) or fewer bins "
                         f"(got {bins})")
    coeffs, fitted = coeffs.reshape(bins, bins, 3, 6), fitted.reshape(bins, bins)
    return {"coeffs": _nearest_fill(coeffs, fitted), "fitted": fitted, "presses": presses.reshape(bins, bins),
            "samples": samples.reshape(bins, bins), "background": bg, "bins": bins, "sigma_px": float(sigma_px),
            "pixel_m": pixel_m, "ball_radius_m": ball_radius_m, "shape": (h, w)}
