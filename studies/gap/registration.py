"""Register real frames on simulated ones: the turn, shift and scale between the two, in
closed form, before any fit.

A fit of a misalignment that starts at zero offset on a smooth image has no gradient to
follow a shift of ten pixels (issue 74: a frame turned by 3.2 degrees and shifted by
10 px was named blur, its misalignment fit moving 1 % from its start). Image registration
finds such a move directly, so the misalignment candidate starts where registration puts
it and the fit refines it from there.

``register`` compares one real and one simulated image, each the per-pixel median of
their frames (a contact sits at another place in each frame, so the median keeps the
membrane and drops the contacts; where the datasets hold no-contact frames, the median
of those). It draws starts from

- phase correlation of the two (``skimage.registration.phase_cross_correlation``): the
  shift, in closed form;
- the Fourier-Mellin transform: the phase correlation of the log-polar magnitude spectra
  (``skimage.transform.warp_polar``), which a shift leaves alone, gives the turn and the
  magnification;

then refines each by OpenCV's enhanced correlation coefficient maximisation
(``cv2.findTransformECC``, a similarity: turn, shift and scale, coarse to fine over a
Gaussian pyramid), and keeps the start whose refinement correlates best. The match is
reliable when the correlation reaches ``MIN_CORRELATION`` and the images have texture to
match (``MIN_TEXTURE``) and are not mostly saturated (``MAX_SATURATED``); otherwise it
says why and the fit starts from zero.

The move is returned in the catalogue's convention (``effects.source_coordinates``): a
real pixel x shows the simulated one at c + s R(theta) (x - c) + (du, dv), c the image
centre, in full-resolution pixels.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

#: The smallest ECC correlation (in [-1, 1]) of a reliable match.
MIN_CORRELATION = 0.8
#: The smallest spread of the reference's gradient magnitude (linear RGB per pixel, at
#: the working resolution) inside the compared area: below it the image is flat, and a
#: shift cannot be told from none.
MIN_TEXTURE = 2e-3
#: A match is unreliable when more than this share of the compared pixels is clipped at
#: 0 or 1 in either image.
MAX_SATURATED = 0.5
#: Levels of the coarse-to-fine pyramid (each halves the image): a 12 px shift at the
#: full resolution is 1.5 px at the coarsest level of a half-resolution working image.
PYRAMID_LEVELS = 3
#: ECC's stop per level: this many iterations, or a step below this (px).
ECC_ITERATIONS = 100
ECC_EPS = 1e-5
#: ECC's Gaussian pre-smoothing, px (odd; OpenCV's gaussFiltSize).
ECC_SMOOTHING_PX = 5
#: ``register_contacts``: a pair's contact is its change from the median frame where that
#: reaches this (linear RGB, grey) ...
CONTACT_CHANGE = 0.02
#: ... at least this many contacts must agree on one move ...
MIN_CONTACTS = 4
#: ... within this many pixels (at the working resolution), found by this many RANSAC trials.
CONTACT_RESIDUAL_PX = 1.0
RANSAC_TRIALS = 200
#: Turns (degrees) tried as starts besides the Fourier-Mellin estimate: a smooth, nearly
#: round image's spectrum can hide its turn.
TURN_STARTS_DEG = (-6.0, 0.0, 6.0)


@dataclass(frozen=True)
class Registration:
    """A registration of real frames on simulated ones.

    rotation_rad, du_px, dv_px : the move in the catalogue's convention (module doc),
        full-resolution pixels; zero where the match is not reliable (the scale is left
        to the fit: ECC here is Euclidean);
    correlation : ECC's correlation coefficient of the best match (None where none ran);
    reliable : whether the match is one to start from; reason : why not ("" if it is);
    frames : what was compared.
    """

    rotation_rad: float = 0.0
    du_px: float = 0.0
    dv_px: float = 0.0
    correlation: float | None = None
    reliable: bool = False
    reason: str = ""
    frames: str = ""

    def params(self) -> dict:
        """The misalignment parameters of this move (zero where it is unreliable)."""
        if not self.reliable:
            return {"du_px": 0.0, "dv_px": 0.0, "rotation_rad": 0.0}
        return {"du_px": self.du_px, "dv_px": self.dv_px, "rotation_rad": self.rotation_rad}

    def to_dict(self) -> dict:
        return {**asdict(self), "rotation_deg": math.degrees(self.rotation_rad)}


def grey(images: np.ndarray) -> np.ndarray:
    """(..., H, W) float32 mean over the colour channels of (..., H, W, 3) images."""
    return np.asarray(images, np.float32).mean(axis=-1)


def representative(images: np.ndarray, no_contact: np.ndarray | None = None) -> tuple[np.ndarray, str]:
    """(H, W) the frame registration compares, and what it is: the per-pixel median of the
    no-contact frames where ``no_contact`` (N,) bool marks any, else of every frame
    (contacts move from frame to frame, so the median keeps what the frames share).
    images : (N, H, W, 3) or (N, H, W)."""
    images = np.asarray(images, np.float32)
    if images.ndim == 4:
        images = grey(images)
    if no_contact is not None and np.any(no_contact):
        kept = images[np.asarray(no_contact, bool)]
        return np.median(kept, axis=0), f"median of {len(kept)} no-contact frame(s)"
    return np.median(images, axis=0), f"median of {len(images)} frames"


def fourier_mellin_turn(reference: np.ndarray, moving: np.ndarray) -> float:
    """The turn (radians, counter-clockwise as displayed: rows down) that takes ``moving``
    to ``reference``, from the phase correlation of their magnitude spectra in log-polar
    coordinates: a shift changes only the spectra's phases, so it drops out."""
    from skimage.filters import difference_of_gaussians, window
    from skimage.registration import phase_cross_correlation
    from skimage.transform import warp_polar

    def spectrum(image: np.ndarray) -> np.ndarray:
        band = difference_of_gaussians(image, 1, 8) * window("hann", image.shape)
        return np.abs(np.fft.fftshift(np.fft.fft2(band)))

    radius = min(reference.shape) // 2
    polar = [warp_polar(spectrum(i), radius=radius, output_shape=(360, radius), scaling="log")[:, :radius // 2]
             for i in (reference, moving)]
    shift, _, _ = phase_cross_correlation(polar[0], polar[1], upsample_factor=10, normalization=None)
    return math.radians(float(shift[0]))


def _ecc(reference: np.ndarray, moving: np.ndarray, area: np.ndarray, turn: float,
         shift_rc: tuple[float, float]) -> tuple[float, np.ndarray]:
    """ECC's Euclidean refinement, coarse to fine over ``PYRAMID_LEVELS``, of the warp that
    takes a reference pixel (x, y) to the moving image's, started at ``turn`` about the
    image centre and the moving image displaced by ``shift_rc`` (rows, cols);
    (correlation, (2, 3) warp), correlation nan where OpenCV's iteration failed."""
    import cv2

    criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, ECC_ITERATIONS, ECC_EPS)
    levels = [(np.ascontiguousarray(reference, np.float32), np.ascontiguousarray(moving, np.float32),
               area.astype(np.uint8))]
    while len(levels) < PYRAMID_LEVELS and min(levels[-1][0].shape) >= 64:
        r, m, a = levels[-1]
        small = cv2.pyrDown(r)
        levels.append((small, cv2.pyrDown(m),
                       cv2.resize(a, (small.shape[1], small.shape[0]), interpolation=cv2.INTER_NEAREST)))
    h, w = reference.shape
    cx, cy = (w - 1) / 2.0, (h - 1) / 2.0
    c, s = math.cos(turn), math.sin(turn)
    warp = np.array([[c, -s, 0.0], [s, c, 0.0]])
    warp[:, 2] = np.array([cx, cy]) - warp[:, :2] @ np.array([cx, cy]) - np.array([shift_rc[1], shift_rc[0]])
    warp = warp.astype(np.float32)
    warp[:, 2] /= 2.0 ** (len(levels) - 1)
    rho = float("nan")
    for k, (r, m, a) in enumerate(reversed(levels)):
        if k:
            warp[:, 2] *= 2.0
        try:
            rho, warp = cv2.findTransformECC(r, m, warp, cv2.MOTION_EUCLIDEAN, criteria, a, ECC_SMOOTHING_PX)
        except cv2.error:
            return float("nan"), warp
    return float(rho), warp


def register(real: np.ndarray, sim: np.ndarray, area: np.ndarray | None = None, factor: int = 1,
             centre: tuple[float, float] | None = None, frames: str = "") -> Registration:
    """The move of ``real`` against ``sim`` ((H, W) images, e.g. ``representative``'s, at a
    working resolution of 1/``factor`` of the full one), compared over ``area`` ((H, W)
    bool, default everywhere): the best ECC refinement (module doc) over starts from
    phase correlation, the Fourier-Mellin turn and ``TURN_STARTS_DEG``; where no match is
    reliable, a Registration saying why, at zero."""
    from skimage.registration import phase_cross_correlation

    real = np.asarray(real, np.float32)
    sim = np.asarray(sim, np.float32)
    if real.shape != sim.shape or real.ndim != 2:
        raise ValueError(f"register needs two (H, W) images of one shape, got {real.shape} and {sim.shape}")
    area = np.ones(real.shape, bool) if area is None else np.asarray(area, bool)
    if area.shape != real.shape:
        raise ValueError(f"register: the area is {area.shape}, the images {real.shape}")
    if not (np.isfinite(real).all() and np.isfinite(sim).all()):
        raise ValueError("register: the images hold NaN or infinite values")
    if area.sum() < 64:
        return Registration(reason=f"only {int(area.sum())} pixels to compare", frames=frames)
    clipped = max(float(np.mean((x[area] <= 0.0) | (x[area] >= 1.0))) for x in (real, sim))
    if clipped > MAX_SATURATED:
        return Registration(reason=f"{100 * clipped:.0f}% of the compared pixels are clipped at 0 or 1 (more than "
                                   f"{100 * MAX_SATURATED:.0f}%): no reliable match", frames=frames)
    texture = min(_texture(x, area) for x in (real, sim))
    if texture < MIN_TEXTURE:
        return Registration(reason=f"the frames are flat (gradient spread {texture:.2g} < {MIN_TEXTURE:g}): no "
                                   "reliable match", frames=frames)
    shift, _, _ = phase_cross_correlation(np.where(area, real, 0), np.where(area, sim, 0), upsample_factor=4,
                                          normalization=None)
    turns = {round(fourier_mellin_turn(real, sim), 4), *(math.radians(t) for t in TURN_STARTS_DEG)}
    best = (-np.inf, None)
    for turn in sorted(turns):
        for start in (tuple(shift), (0.0, 0.0)):
            rho, warp = _ecc(real, sim, area, turn, start)
            if np.isfinite(rho) and rho > best[0]:
                best = (rho, warp)
    rho, warp = best
    if warp is None:
        return Registration(reason="ECC did not converge from any start: no reliable match", frames=frames)
    # warp: x_s = A x + b (x, y order); the catalogue's x_s = c + R (x - c) + d.
    h, w = real.shape
    c = np.array([(w - 1) / 2.0, (h - 1) / 2.0]) if centre is None else np.array([centre[1], centre[0]], float)
    d = warp[:, 2] + warp[:, :2] @ c - c
    turn = math.atan2(float(warp[1, 0]), float(warp[0, 0]))
    if rho < MIN_CORRELATION:
        return Registration(correlation=float(rho), reason=f"the best match correlates {rho:.2f} (< "
                            f"{MIN_CORRELATION}): no reliable match", frames=frames)
    return Registration(rotation_rad=turn, du_px=float(d[0]) * factor, dv_px=float(d[1]) * factor,
                        correlation=float(rho), reliable=True, frames=frames)


def register_contacts(real: np.ndarray, sim: np.ndarray, factor: int = 1,
                      centre: tuple[float, float] | None = None) -> Registration:
    """The move of the frame from its contacts: each pair's contact, found in its change
    from the frames' median (``representative``), is located in the simulated frame (the
    centroid of its change) and in the real one (that plus the phase correlation of the
    two changes), and a turn and shift is fitted to those correspondences by RANSAC
    (``skimage.measure.ransac`` over ``EuclideanTransform``), so that a pair whose real
    contact differs from the simulated one is left out. Where only the contacts turn with
    the frame (a solid background inside a round image circle) they alone show its turn.
    real, sim : (N, H, W). Unreliable with fewer than ``MIN_CONTACTS`` usable contacts
    or inliers."""
    from skimage.measure import ransac
    from skimage.registration import phase_cross_correlation
    from skimage.transform import EuclideanTransform

    real = np.asarray(real, np.float32)
    sim = np.asarray(sim, np.float32)
    if real.shape != sim.shape or real.ndim != 3:
        raise ValueError(f"register_contacts needs two (N, H, W) stacks of one shape, got {real.shape} and {sim.shape}")
    frames = f"the contacts of {len(real)} pairs"
    change_r = real - np.median(real, axis=0)
    change_s = sim - np.median(sim, axis=0)
    src, dst = [], []
    for r, s in zip(change_r, change_s):
        weight = np.abs(s)
        peak = float(weight.max())
        if peak < CONTACT_CHANGE:
            continue
        weight = np.where(weight > 0.25 * peak, weight, 0.0)
        v, u = np.nonzero(weight)
        w = weight[v, u]
        at = np.array([(u * w).sum() / w.sum(), (v * w).sum() / w.sum()])
        shift, error, _ = phase_cross_correlation(r, s, upsample_factor=10, normalization=None)
        src.append(at)
        dst.append(at + shift[::-1])  # (x, y): real shows the simulated contact moved by the shift
    if len(src) < MIN_CONTACTS:
        return Registration(reason=f"{len(src)} pairs have a contact to register (fewer than {MIN_CONTACTS})",
                            frames=frames)
    src, dst = np.array(src), np.array(dst)
    # The catalogue samples the simulated frame at c + R (x - c) + d for a real pixel x: the
    # map real -> simulated, so estimate dst -> src.
    model, inliers = ransac((dst, src), EuclideanTransform, min_samples=2, residual_threshold=CONTACT_RESIDUAL_PX,
                            max_trials=RANSAC_TRIALS, rng=0)
    if model is None or inliers is None or inliers.sum() < MIN_CONTACTS:
        kept = 0 if inliers is None else int(inliers.sum())
        return Registration(reason=f"{kept} of {len(src)} contacts agree on one move (fewer than {MIN_CONTACTS})",
                            frames=frames)
    h, w = real.shape[1:]
    c = np.array([(w - 1) / 2.0, (h - 1) / 2.0]) if centre is None else np.array([centre[1], centre[0]], float)
    A, b = model.params[:2, :2], model.params[:2, 2]
    d = b + A @ c - c
    return Registration(rotation_rad=float(model.rotation), du_px=float(d[0]) * factor, dv_px=float(d[1]) * factor,
                        reliable=True, frames=f"{frames} ({int(inliers.sum())} of {len(src)} contacts agree)")


def _texture(image: np.ndarray, area: np.ndarray) -> float:
    gv, gu = np.gradient(image)
    return float(np.std(np.hypot(gu, gv)[area]))
