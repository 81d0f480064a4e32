"""Where each field fails, by class of region of the membrane (``scenes.curvature``).

``pixel_regions`` classes the membrane point each pixel sees; ``region_errors`` scores a
field's change per class against predicting no change, pixel by pixel;
``contact_region_table`` does so per contact; ``failures`` names the classes.
"""

from __future__ import annotations

import numpy as np
import trimesh
from scipy import stats

from scenes.camera import Camera, cast_rays
from scenes.curvature import CLASSES, classify, vertex_curvatures

from .summary import CONFIDENCE, N_RESAMPLES, bootstrap_mean


def pixel_regions(mesh: trimesh.Trimesh, camera: Camera) -> np.ndarray:
    """(h, w) str: the class of region (``scenes.curvature.CLASSES``) of the membrane point
    each pixel of ``camera`` sees, from the curvatures at the mesh's vertices interpolated
    to the hit; "" where the ray misses the membrane."""
    samples = cast_rays(mesh, camera)
    k = samples.interpolate(mesh, vertex_curvatures(mesh))
    return samples.scatter(classify(k).astype(object), fill="").astype(str)


def region_errors(change_pred: np.ndarray, change_ref: np.ndarray, pixels: np.ndarray, regions: np.ndarray,
                  seed: int, confidence: float = CONFIDENCE, n_resamples: int = N_RESAMPLES) -> dict:
    """Where a predicted contact change goes wrong, by class of region of the membrane.

    change_pred, change_ref : (K, h, w, 3), the calibrated prediction and the reference.
    pixels : (K, h, w) bool, the pixels each contact is scored on (near it, reliable).
    regions : (h, w) str, the class of the membrane point each pixel sees (``pixel_regions``).

    For each class c and contact k, e_k sums |pred - ref| over k's pixels of class c and
    b_k sums |ref|, the error of predicting no change there. The ratio sum(e) / sum(b) is
    below 1 where the prediction tracks the contact and at or above 1 where it does no
    better than no change. Its percentile-bootstrap interval resamples contacts (the
    pairs (e_k, b_k)). Returns class -> {"ratio", "ci_low", "ci_high", "pixels",
    "contacts"}, for the classes that at least 2 contacts reach with some signal (b > 0).
    """
    if change_pred.shape != change_ref.shape or change_pred.shape[:3] != pixels.shape or pixels.shape[1:] != regions.shape:
        raise ValueError(f"change_pred, change_ref (K, h, w, 3), pixels (K, h, w) and regions (h, w) must agree, got "
                         f"{change_pred.shape}, {change_ref.shape}, {pixels.shape}, {regions.shape}")
    error = np.abs(change_pred - change_ref).sum(axis=-1)
    signal = np.abs(change_ref).sum(axis=-1)
    out = {}
    for cls in CLASSES:
        where = pixels & (regions == cls)[None]
        e, b = (np.where(where, error, 0.0).sum(axis=(1, 2)), np.where(where, signal, 0.0).sum(axis=(1, 2)))
        reached = b > 0
        if reached.sum() < 2:
            continue
        e, b = e[reached], b[reached]
        ratio = lambda e, b, axis=-1: e.sum(axis=axis) / b.sum(axis=axis)  # noqa: E731
        if np.ptp(e / b) == 0:
            lo = hi = float(ratio(e, b))
        else:
            res = stats.bootstrap((e, b), ratio, paired=True, vectorized=True, confidence_level=confidence,
                                  n_resamples=n_resamples, method="percentile", rng=np.random.default_rng(seed))
            lo, hi = float(res.confidence_interval.low), float(res.confidence_interval.high)
        out[cls] = {"ratio": float(ratio(e, b)), "ci_low": lo, "ci_high": hi, "pixels": int(where.sum()),
                    "contacts": int(reached.sum())}
    return out


def contact_region_table(per_contact: dict[str, list[dict]], no_change: list[dict], regions: list[str],
                         seed: int) -> dict:
    """Change MAE per field over the contacts of each class of region (that of the point
    each contact presses), next to the no-change baseline's, with bootstrap intervals;
    and, per field, the paired interval of (no change - field): above 0, the field beats
    predicting no change on those contacts. Classes with fewer than 2 contacts are left out.

    per_contact : field -> per-contact metrics; no_change : the baseline's; regions : the
    class of each contact, in the same order.
    """
    out = {}
    for cls in CLASSES:
        idx = [k for k, r in enumerate(regions) if r == cls]
        if len(idx) < 2:
            continue
        base = np.array([no_change[k]["change"]["mae"] for k in idx])
        row = {"contacts": len(idx), "no_change": bootstrap_mean(base, seed)}
        for method, rows in per_contact.items():
            mae = np.array([rows[k]["change"]["mae"] for k in idx])
            row[method] = {"mae": bootstrap_mean(mae, seed), "no_change_minus_field": bootstrap_mean(base - mae, seed)}
        out[cls] = row
    return out


def failures(results: dict) -> dict[str, dict[str, list[str]]]:
    """Per field, the classes of region where it fails (its pixel error ratio's interval
    lies at or above 1: no better than predicting no change), where it tracks the
    contact (the interval lies below 1), and where the numbers cannot tell."""
    out = {}
    for method, table in results["pixel_regions"]["ratio"].items():
        out[method] = {
            "fails": [c for c, r in table.items() if r["ci_low"] >= 1.0],
            "tracks": [c for c, r in table.items() if r["ci_high"] < 1.0],
            "unclear": [c for c, r in table.items() if r["ci_low"] < 1.0 <= r["ci_high"]],
        }
    return out
