"""How the diagnosis judges a change to the simulator: paired improvements of the gap's
metrics with their bootstrap intervals, and summaries of per-sample metrics.

The metrics themselves (MAE, SSIM and PSNR of each sample, full frame and masked: see
``scenes.image_stats.per_sample``) and the bootstrap interval of a mean
(``scenes.image_stats.bootstrap_interval``) live in ``scenes.image_stats``.
"""

from __future__ import annotations

import numpy as np

from scenes.image_stats import METRICS, bootstrap_interval

#: Which way is better for each metric.
HIGHER_IS_BETTER = {"mae": False, "ssim": True, "psnr": True}


def improvement(before: np.ndarray, after: np.ndarray, metric: str, confidence: float = 0.95,
                resamples: int = 2000, seed: int = 0) -> dict:
    """Paired improvement of a metric, sample by sample, with its bootstrap interval.

    The improvement is before - after for MAE and after - before for SSIM and PSNR, so
    positive is better for all three. ``significant`` means the interval's lower end is
    above zero. ``share`` is the improvement as a fraction of the mean MAE before (MAE
    only: the share of the gap closed).
    """
    before, after = np.asarray(before, np.float64), np.asarray(after, np.float64)
    both = np.isfinite(before) & np.isfinite(after)  # a sample whose region was empty counts on neither side
    before, after = before[both], after[both]
    gain = (after - before) if HIGHER_IS_BETTER[metric] else (before - after)
    ci = bootstrap_interval(gain, confidence, resamples, seed)
    out = {**ci, "significant": bool(ci["low"] > 0)}
    if metric == "mae":
        gap = float(before.mean())
        out["share"] = ci["mean"] / gap if gap > 0 else 0.0
        out["share_low"] = ci["low"] / gap if gap > 0 else 0.0
        out["share_high"] = ci["high"] / gap if gap > 0 else 0.0
    return out


def summarise(values: dict, confidence: float = 0.95, seed: int = 0) -> dict:
    """Means with intervals of a ``per_sample`` result: {full|masked: {metric: ci}}; a
    metric left out (SSIM of a quick judgement, all NaN) is left out here too."""
    return {k: {m: bootstrap_interval(v[m], confidence, seed=seed) for m in METRICS if _measured(v.get(m))}
            for k, v in values.items()}


def _measured(values) -> bool:
    """Whether a metric was measured (``per_sample(ssim=False)`` leaves SSIM as NaN)."""
    return values is not None and not np.all(np.isnan(np.asarray(values, np.float64)))


def group_means(values: np.ndarray, keys: list) -> dict:
    """Mean of per-sample values per group key (object, tap position): {key: {mean, n}}."""
    values = np.asarray(values, np.float64)
    out = {}
    for key in sorted(set(keys), key=str):
        sel = np.array([k == key for k in keys])
        out[str(key)] = {"mean": float(values[sel].mean()), "n": int(sel.sum())}
    return out
