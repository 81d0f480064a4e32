"""Image metrics of the gap and their confidence intervals.

MAE, SSIM and PSNR (scikit-image) of each sample, both as the paper computed them (the
full frame, black border included) and masked to the sensor's image circle; bootstrap
confidence intervals of means and of paired differences (scipy.stats.bootstrap, samples
resampled as units).
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from scipy import stats
from skimage.metrics import structural_similarity

METRICS = ("mae", "ssim", "psnr")
#: The scopes every sample is measured in: the whole frame and the image circle.
SCOPES = ("full", "masked")
#: Which way is better for each metric.
HIGHER_IS_BETTER = {"mae": False, "ssim": True, "psnr": True}
#: PSNR of identical images is infinite; it is capped here (dB) so means stay finite.
PSNR_CAP_DB = 100.0


def _psnr(mse: np.ndarray) -> np.ndarray:
    with np.errstate(divide="ignore"):
        return np.minimum(10.0 * np.log10(1.0 / np.maximum(mse, 1e-300)), PSNR_CAP_DB)


def per_sample(real: np.ndarray, pred: np.ndarray, mask: np.ndarray, ssim: bool = True,
               areas: np.ndarray | None = None, regions: dict[str, np.ndarray] | None = None,
               contact: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Metrics of each sample: {"full": {mae, ssim, psnr}, "masked": {...}}, arrays (N,).

    real, pred : (N, H, W, 3) or (H, W, 3) float in [0, 1]; mask : (H, W) bool, the
    sensor's image circle. SSIM is scikit-image's (7x7 window, data range 1); its masked
    value is the mean of the SSIM map over the mask. ``ssim=False`` leaves SSIM out (NaN),
    for quick comparisons: it costs most of the time. ``areas`` (N, H, W) bool, optional:
    each sample is measured only there ("full") and there within the mask ("masked"),
    for samples that are parts of one image. ``regions`` {name: (H, W) bool}, optional:
    each adds a scope of that name, measured within the mask there (no ``areas`` then).
    ``contact`` (N, H, W) bool, optional: each sample's contact region
    (``scenes.captures.press_regions``), a scope "contact" measured within the mask there
    (a sample whose region is empty gets NaN).
    """
    real, pred = np.asarray(real), np.asarray(pred)
    if real.shape != pred.shape:
        raise ValueError(f"real and predicted images differ in shape: {real.shape} vs {pred.shape}")
    if real.ndim == 3:
        real, pred = real[None], pred[None]
    if real.ndim != 4 or real.shape[-1] != 3 or mask.shape != real.shape[1:3]:
        raise ValueError(f"images must be (N, H, W, 3) with an (H, W) mask, got {real.shape} and {mask.shape}")
    if areas is not None and areas.shape != real.shape[:3]:
        raise ValueError(f"areas must be (N, H, W) like the images, got {areas.shape} for {real.shape}")
    regions = {} if regions is None else regions
    if regions and areas is not None:
        raise ValueError("per_sample measures regions of whole images: give regions or areas, not both")
    for name, region in regions.items():
        if name in SCOPES or region.shape != mask.shape or not (region & mask).any():
            raise ValueError(f"region {name!r} must be an (H, W) bool mask like the image circle's, with pixels inside "
                             f"it, and not named full or masked; got shape {region.shape}")
    if contact is not None and (np.shape(contact) != real.shape[:3] or np.asarray(contact).dtype != bool):
        raise ValueError(f"contact must be (N, H, W) bool like the images {real.shape[:3]}, got "
                         f"{np.shape(contact)} {getattr(contact, 'dtype', '')}")
    n = len(real)
    out = {k: {m: np.empty(n) for m in METRICS} for k in (*SCOPES, *regions, *(("contact",) if contact is not None
                                                                                else ()))}

    def one(i: int) -> None:
        a, b = real[i].astype(np.float64), pred[i].astype(np.float64)
        err = a - b
        if ssim:
            # float32 inputs keep scikit-image in float32: twice as fast, same to 1e-6.
            _, smap = structural_similarity(real[i].astype(np.float32), pred[i].astype(np.float32),
                                            channel_axis=-1, data_range=1.0, full=True)
        else:
            smap = np.full(a.shape[:2], np.nan)
        sq = np.square(err)
        frame = slice(None) if areas is None else areas[i]
        inner = mask if areas is None else mask & areas[i]
        out["full"]["mae"][i] = np.abs(err[frame]).mean()
        out["full"]["psnr"][i] = _psnr(sq[frame].mean())
        out["full"]["ssim"][i] = smap[frame].mean()
        out["masked"]["mae"][i] = np.abs(err[inner]).mean()
        out["masked"]["psnr"][i] = _psnr(sq[inner].mean())
        out["masked"]["ssim"][i] = smap[inner].mean()
        for name, region in (*regions.items(), *((("contact", contact[i]),) if contact is not None else ())):
            inner = mask & region
            if not inner.any():
                for m in METRICS:
                    out[name][m][i] = np.nan
                continue
            out[name]["mae"][i] = np.abs(err[inner]).mean()
            out[name]["psnr"][i] = _psnr(sq[inner].mean())
            out[name]["ssim"][i] = smap[inner].mean()

    # scikit-image's filters release the GIL: samples in threads use every core.
    with ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
        list(pool.map(one, range(n)))
    return out


def mean_ci(values: np.ndarray, confidence: float = 0.95, resamples: int = 2000, seed: int = 0) -> dict:
    """Mean of per-sample values with a percentile bootstrap interval: {mean, low, high}.
    NaN values (a sample whose region was empty) are left out; all NaN gives NaN."""
    values = np.asarray(values, dtype=np.float64)
    values = values[np.isfinite(values)] if np.isnan(values).any() else values
    if len(values) == 0:
        return {"mean": float("nan"), "low": float("nan"), "high": float("nan")}
    mean = float(values.mean())
    if len(values) < 2 or np.ptp(values) == 0:
        return {"mean": mean, "low": mean, "high": mean}
    res = stats.bootstrap((values,), np.mean, confidence_level=confidence, n_resamples=resamples,
                          method="percentile", random_state=np.random.default_rng(seed))
    return {"mean": mean, "low": float(res.confidence_interval.low), "high": float(res.confidence_interval.high)}


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
    ci = mean_ci(gain, confidence, resamples, seed)
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
    return {k: {m: mean_ci(v[m], confidence, seed=seed) for m in METRICS if _measured(v.get(m))}
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


def low_passed_variance(variance: np.ndarray, sigma: float) -> np.ndarray:
    """(H, W, C) the variance of independent pixels' values once low-passed by a Gaussian
    of ``sigma`` pixels (scipy.ndimage's, 'nearest' borders): sum_j w_j^2 v_j per pixel."""
    if sigma <= 0:
        return variance
    from scipy import ndimage

    size = 2 * int(4 * sigma + 0.5) + 1  # gaussian_filter's kernel (truncate 4)
    delta = np.zeros((size, size), np.float64)
    delta[size // 2, size // 2] = 1.0
    weights = ndimage.gaussian_filter(delta, sigma, mode="constant")
    return ndimage.convolve(np.asarray(variance, np.float64), (weights ** 2)[..., None], mode="nearest")


def mae_floor(variance: np.ndarray, area: np.ndarray) -> float:
    """The MAE that zero-mean Gaussian noise of this per-pixel ``variance`` alone makes
    over ``area`` (a bool mask of its pixels): sqrt(2 / pi) sigma, averaged."""
    return float(np.sqrt(2 / np.pi) * np.sqrt(np.asarray(variance)[area]).mean())
