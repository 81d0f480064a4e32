"""Calibration of a fast-path field's frames onto the reference: per-channel gain >= 0 and offset.

Arrays in, arrays out. Why the study calibrates each contact leave-one-out, with the gain
set by the other contacts' changes, is in ``studies.pbr_field_comparison.study``.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import lsq_linear


def fit_affine(fast: np.ndarray, ref: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-channel gain >= 0 and offset minimising |gain fast + offset − ref|² inside the mask.

    The gain is bounded at 0 because the map converts units: it must not turn the fast
    path's brightening into a darkening (a field whose contact signal anticorrelates with
    the reference gets gain 0, i.e. predicts no change).

    fast, ref : (..., h, w, 3) frames; mask : (h, w) bool.  Returns gain (3,), offset (3,).
    """
    if fast.shape != ref.shape or fast.shape[-1] != 3 or fast.shape[-3:-1] != mask.shape:
        raise ValueError(f"fast and ref must be (..., h, w, 3) with mask (h, w), got {fast.shape}, {ref.shape}, "
                         f"{mask.shape}")
    x, y = fast[..., mask, :].reshape(-1, 3), ref[..., mask, :].reshape(-1, 3)
    gain, offset = np.empty(3), np.empty(3)
    for c in range(3):
        A = np.stack([x[:, c], np.ones(len(x))], axis=1).astype(np.float64)
        fit = lsq_linear(A, y[:, c].astype(np.float64), bounds=([0.0, -np.inf], [np.inf, np.inf]))
        gain[c], offset[c] = fit.x
    return gain, offset


def fit_gain(change_fast: np.ndarray, change_ref: np.ndarray, region: np.ndarray) -> np.ndarray:
    """Per-channel gain >= 0 minimising |gain change_fast − change_ref|² over the region.

    change_fast, change_ref : (..., h, w, 3) contact changes; region : (h, w) bool.
    A least-squares line through the origin, clipped at 0 (the exact bounded solution
    for one parameter). Returns (3,).
    """
    if change_fast.shape != change_ref.shape or change_fast.shape[-3:-1] != region.shape:
        raise ValueError(f"change_fast and change_ref must be (..., h, w, 3) with region (h, w), got "
                         f"{change_fast.shape}, {change_ref.shape}, {region.shape}")
    f = change_fast[..., region, :].reshape(-1, 3).astype(np.float64)
    r = change_ref[..., region, :].reshape(-1, 3).astype(np.float64)
    ff = (f * f).sum(axis=0)
    return np.where(ff > 0, np.clip((f * r).sum(axis=0) / np.where(ff > 0, ff, 1.0), 0.0, None), 0.0)


def leave_one_out_calibration(fast: np.ndarray, ref: np.ndarray, region: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Calibration of each contact k from the other contacts and the no-contact frame.

    The gain (>= 0) is fitted to the contact changes of every contact but k
    (``fit_gain``), so that it is set by the contact signal and not by the no-contact
    image; the offset then matches the no-contact frame in the least-squares sense.

    fast, ref : (1 + K, h, w, 3), frame 0 without contact; region : (h, w) bool.
    Returns gains, offsets (K, 3).
    """
    K = len(fast) - 1
    if K < 2:
        raise ValueError(f"leave-one-out calibration needs at least 2 contacts, got {K}")
    change_fast, change_ref = fast[1:] - fast[:1], ref[1:] - ref[:1]
    gains = np.stack([fit_gain(np.delete(change_fast, k, axis=0), np.delete(change_ref, k, axis=0), region)
                      for k in range(K)])
    offsets = np.stack([(ref[0][region] - g * fast[0][region]).mean(axis=0) for g in gains])
    return gains, offsets
