"""Per-contact metrics of a field's frames against the reference, and the pixels they are taken over.

Three kinds (KINDS): the full frame, the contact change over the mask, and the contact
change near the contact; the no-change baseline's; the reference pixels to trust
(``reliable_pixels``) and those far from a contact (``far_from_contact``); the reference
noise's floor on MAE (``noise_floor``).
"""

from __future__ import annotations

import math

import numpy as np
from scipy import ndimage

from scenes.image_stats import image_metrics, mae_floor, pearson

from .frames import downsample

#: Reference pixels whose standard error exceeds this fraction of the no-contact frame's
#: median are left out of every fit and metric (see ``reliable_pixels``).
MAX_STANDARD_ERROR = 0.5
METRICS = ("mae", "ssim", "psnr_db")
#: full frames; contact change over the mask; contact change near the contact only.
KINDS = ("full", "change", "contact")
CHANGE_KINDS = ("change", "contact")
#: Calibration-free: Pearson's r of the field's contact change with the reference's, near
#: the contact (reported with the "contact" kind).
CORRELATION = "pearson_r"


def _metrics(expected: np.ndarray, actual: np.ndarray, mask: np.ndarray, data_range: float,
             region: np.ndarray | None = None) -> dict[str, float]:
    """``scenes.image_stats.image_metrics`` under this study's names (METRICS: PSNR in dB)."""
    m = image_metrics(expected, actual, mask, data_range, region)
    return {"mae": m["mae"], "ssim": m["ssim"], "psnr_db": m["psnr"]}


def change_metrics(change_ref: np.ndarray, change_pred: np.ndarray, mask: np.ndarray, region: np.ndarray,
                   near: np.ndarray) -> dict:
    """Metrics of a predicted contact change (h, w, 3) over the region ("change") and over
    its pixels near the contact ("contact"); data_range: the reference change's span."""
    span = float(np.ptp(change_ref[region]))
    span = span if span > 0 else 1.0
    return {"change": _metrics(change_ref, change_pred, mask, span, region),
            "contact": _metrics(change_ref, change_pred, mask, span, near & region)}


def contact_metrics(
    fast: np.ndarray, ref: np.ndarray, gains: np.ndarray, offsets: np.ndarray, mask: np.ndarray,
    region: np.ndarray, near: np.ndarray,
) -> list[dict]:
    """Full-frame and change metrics of each contact for one field.

    fast, ref : (1 + K, h, w, 3), frame 0 without contact, ref normalised.
    gains, offsets : (K, 3), the calibration of each contact.
    mask : (h, w) bool, the image circle; region : (h, w) bool, where the metrics average.
    near : (K, h, w) bool, pixels near each contact (see ``far_from_contact``).
    """
    out = []
    for k in range(1, len(fast)):
        g, o = gains[k - 1], offsets[k - 1]
        change = fast[k] - fast[0]
        out.append({
            "full": _metrics(ref[k], g * fast[k] + o, mask, 1.0, region),
            **change_metrics(ref[k] - ref[0], g * change, mask, region, near[k - 1]),
        })
        out[-1]["contact"][CORRELATION] = pearson(change[near[k - 1] & region], (ref[k] - ref[0])[near[k - 1] & region])
    return out


def no_change_metrics(ref: np.ndarray, mask: np.ndarray, region: np.ndarray, near: np.ndarray) -> list[dict]:
    """Change metrics of the baseline that predicts no change at all, per contact.

    ref : (1 + K, h, w, 3), frame 0 without contact.  A field that does not beat this
    baseline does not track the contact.
    """
    return [change_metrics(ref[k] - ref[0], np.zeros_like(ref[k]), mask, region, near[k - 1])
            for k in range(1, len(ref))]


def reliable_pixels(mean: np.ndarray, variance: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(h, w) bool: pixels whose reference estimate is trustworthy in every frame.

    mean, variance : (F, h, w, 3), the estimates and the variances of their means. A pixel
    is left out when, in any frame and channel, its standard error exceeds
    MAX_STANDARD_ERROR times the median of the first frame inside the mask: the photon
    estimator's rare single-pass spikes, which would otherwise dominate MSE and the
    normalising percentile.
    """
    level = float(np.median(mean[0][mask]))
    if not level > 0:
        raise ValueError(f"the reference is black inside the mask (median {level})")
    error = np.sqrt(np.clip(variance, 0.0, None)).max(axis=(0, -1))
    return error <= MAX_STANDARD_ERROR * level


def far_from_contact(depth: np.ndarray, ref_depth: np.ndarray, shape: tuple[int, int], margin_px: float) -> np.ndarray:
    """(h, w) bool: reference pixels farther than ``margin_px`` (depth-camera px) from any
    pixel where the depth map differs from D_ref."""
    touched = downsample(np.repeat((depth != ref_depth)[..., None], 3, axis=-1).astype(np.float32), shape)[..., 0] > 0
    factor = depth.shape[0] / shape[0]
    return ~ndimage.binary_dilation(touched, iterations=max(1, math.ceil(margin_px / factor)))


def noise_floor(variance: np.ndarray, scale: float, mask: np.ndarray) -> float:
    """MAE a perfect estimate would score from noise of variance (h, w, 3) alone
    (``scenes.image_stats.mae_floor``), in units of ``scale``."""
    return mae_floor(np.clip(variance, 0, None), mask) / scale
