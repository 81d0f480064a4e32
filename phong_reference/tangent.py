"""Tangent vectors at surface points: projection onto the tangent plane, and angles."""

from __future__ import annotations

import numpy as np


def tangent_unit(v: np.ndarray, N: np.ndarray, axis: int = -1) -> tuple[np.ndarray, np.ndarray]:
    """Project vectors onto the planes normal to N and normalise.

    v, N : arrays with the 3 components along ``axis`` (N unit, broadcastable to v).

    Returns
    -------
    t : unit tangent vectors, zero where the projection vanishes.
    valid : bool, where it does not (``axis`` removed).
    """
    t = v - (v * N).sum(axis=axis, keepdims=True) * N
    norm = np.linalg.norm(t, axis=axis, keepdims=True)
    valid = norm > 1e-12
    t = np.divide(t, norm, out=np.zeros_like(t), where=valid)
    return t, np.squeeze(valid, axis=axis)


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle between vectors along the last axis, degrees (need not be unit length);
    NaN where either vector is zero."""
    with np.errstate(invalid="ignore", divide="ignore"):
        cos = (a * b).sum(-1) / (np.linalg.norm(a, axis=-1) * np.linalg.norm(b, axis=-1))
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
