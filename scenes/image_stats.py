"""Statistics of images and of per-sample scores: the project's one home for them.

Image metrics over a region (MAE; SSIM and PSNR from ``skimage.metrics``), the
per-sample metrics a study compares images by, R^2 over pixels, Pearson's r, how
strongly a press shows (the contact strength) and its profile in rings about its centre,
the Monte Carlo noise floor of a render's
variance map, and intervals of a mean over samples: the percentile bootstrap
(``scipy.stats.bootstrap``, samples resampled as units) and Student's t
(``scipy.stats.t``). Every study, and the calibration, imports them from here.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

#: The metrics ``per_sample`` gives each sample, in this order.
METRICS = ("mae", "ssim", "psnr")
#: The scopes ``per_sample`` measures every sample in: the whole frame and the image circle.
SCOPES = ("full", "masked")
#: PSNR of identical images is infinite; ``per_sample`` caps it here (dB) so means stay finite.
PSNR_CAP_DB = 100.0


# --- image metrics --------------------------------------------------------------------------

def ssim_map(expected: np.ndarray, actual: np.ndarray, data_range: float) -> np.ndarray:
    """(H, W, C) scikit-image's SSIM map (7x7 window) of two (H, W, C) images, computed in
    their dtype (float32 is twice as fast as float64 and agrees to 1e-6)."""
    expected, actual = np.asarray(expected), np.asarray(actual)
    if expected.shape != actual.shape or expected.ndim != 3:
        raise ValueError(f"expected and actual must be (H, W, C) images of one shape, got {expected.shape} and "
                         f"{actual.shape}")
    if not data_range > 0:
        raise ValueError(f"data_range must be > 0, got {data_range}")
    return structural_similarity(expected, actual, channel_axis=-1, data_range=data_range, full=True)[1]


def masked_metrics(expected: np.ndarray, actual: np.ndarray, region: np.ndarray | None, data_range: float,
                   ssim: np.ndarray | None = None) -> dict[str, float]:
    """MAE, SSIM and PSNR (dB) of two (H, W, C) float images over a region:
    {"mae", "ssim", "psnr"}.

    region : (H, W) bool, or None for the whole frame. MAE is the mean |actual - expected|
    over the region's pixels and channels; PSNR is scikit-image's over them, with
    ``data_range`` (infinite where the two agree there); SSIM is the mean over the region
    of ``ssim`` (the two images' ``ssim_map``, computed once for several regions), NaN
    without it.
    """
    expected, actual = np.asarray(expected), np.asarray(actual)
    if expected.shape != actual.shape or (region is not None and np.shape(region) != expected.shape[:2]):
        raise ValueError(f"expected and actual must be one shape (H, W, C) with region (H, W), got {expected.shape}, "
                         f"{actual.shape} and {None if region is None else region.shape}")
    e, a = (expected, actual) if region is None else (expected[region], actual[region])
    with np.errstate(divide="ignore", over="ignore"):  # identical images: infinite PSNR, not a warning
        psnr = peak_signal_noise_ratio(e, a, data_range=data_range)
    return {
        "mae": float(np.abs(a - e).mean()),
        "ssim": float("nan") if ssim is None else float((ssim if region is None else ssim[region]).mean()),
        "psnr": float(psnr),
    }


def image_metrics(expected: np.ndarray, actual: np.ndarray, mask: np.ndarray, data_range: float,
                  region: np.ndarray | None = None) -> dict[str, float]:
    """MAE, SSIM and PSNR (dB) of (h, w, 3) images over a region of the mask:
    {"mae", "ssim", "psnr"} (``masked_metrics``).

    Both images are set to zero outside ``mask`` (h, w) bool, so that SSIM's window sees
    no pixel outside it; the metrics average over ``region`` (h, w) bool (default: the
    mask). SSIM is the mean of the float64 SSIM map over the region.
    """
    region = mask if region is None else region
    if expected.shape != actual.shape or expected.shape[:2] != mask.shape or region.shape != mask.shape:
        raise ValueError(f"expected and actual must be (h, w, 3) with mask and region (h, w), got {expected.shape}, "
                         f"{actual.shape}, {mask.shape}, {region.shape}")
    if not data_range > 0:
        raise ValueError(f"data_range must be > 0, got {data_range}")
    if not region.any():
        raise ValueError("region must hold at least one pixel")
    e = np.where(mask[..., None], expected, 0.0).astype(np.float64)
    a = np.where(mask[..., None], actual, 0.0).astype(np.float64)
    return masked_metrics(e, a, region, data_range, ssim_map(e, a, data_range))


def per_sample(real: np.ndarray, pred: np.ndarray, mask: np.ndarray, ssim: bool = True,
               areas: np.ndarray | None = None, regions: dict[str, np.ndarray] | None = None,
               contact: np.ndarray | None = None) -> dict[str, dict[str, np.ndarray]]:
    """Metrics of each sample: {"full": {mae, ssim, psnr}, "masked": {...}}, arrays (N,).

    Both as the paper computed them (the full frame, black border included) and masked to
    the sensor's image circle. real, pred : (N, H, W, 3) or (H, W, 3) float in [0, 1];
    mask : (H, W) bool, the sensor's image circle. SSIM is scikit-image's (7x7 window,
    data range 1, in float32); its masked value is the mean of the SSIM map over the mask.
    PSNR is capped at PSNR_CAP_DB. ``ssim=False`` leaves SSIM out (NaN), for quick
    comparisons: it costs most of the time. ``areas`` (N, H, W) bool, optional: each
    sample is measured only there ("full") and there within the mask ("masked"), for
    samples that are parts of one image. ``regions`` {name: (H, W) bool}, optional: each
    adds a scope of that name, measured within the mask there (no ``areas`` then).
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
        smap = ssim_map(real[i].astype(np.float32), pred[i].astype(np.float32), 1.0) if ssim else None
        scopes = {"full": None if areas is None else areas[i], "masked": mask if areas is None else mask & areas[i]}
        for name, region in (*regions.items(), *((("contact", contact[i]),) if contact is not None else ())):
            scopes[name] = mask & region
        for name, region in scopes.items():
            if region is not None and not region.any():
                for m in METRICS:
                    out[name][m][i] = np.nan
                continue
            got = masked_metrics(a, b, region, 1.0, smap)
            got["psnr"] = np.minimum(got["psnr"], PSNR_CAP_DB)
            for m in METRICS:
                out[name][m][i] = got[m]

    # scikit-image's filters release the GIL: samples in threads use every core.
    with ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
        list(pool.map(one, range(n)))
    return out


# --- agreement over pixels -------------------------------------------------------------------

def r2(pred: np.ndarray, real: np.ndarray, pixels: np.ndarray, weights: np.ndarray | None = None) -> float:
    """Share of the real pixels' variance the prediction explains: 1 - SS_res / SS_tot over
    ``pixels``; NaN where the real pixels do not vary (or weigh nothing).

    pred, real : (H, W) or (H, W, C) float; pixels : bool, the leading dimensions of
    ``real``; weights : float like ``pixels``, optional, each pixel's weight in both sums
    and in the mean (a pixel of a sector drawn twice counts twice).
    """
    pred, real, pixels = np.asarray(pred), np.asarray(real), np.asarray(pixels)
    if pred.shape != real.shape or pixels.shape != real.shape[:pixels.ndim] or pixels.dtype != bool:
        raise ValueError(f"pred and real must be one shape with pixels a bool mask of their leading dimensions, got "
                         f"{pred.shape}, {real.shape} and pixels {pixels.shape} {pixels.dtype}")
    y, p = real[pixels], pred[pixels]
    if weights is None:
        total = float(np.sum((y - y.mean()) ** 2))
        return float(1 - np.sum((y - p) ** 2) / total) if total > 0 else float("nan")
    if np.shape(weights) != pixels.shape:
        raise ValueError(f"weights must be shaped like pixels {pixels.shape}, got {np.shape(weights)}")
    w = np.asarray(weights, np.float64)[pixels]
    if not w.sum() > 0:
        return float("nan")
    mean = np.sum(w * y) / np.sum(w)
    total = np.sum(w * (y - mean) ** 2)
    return float(1 - np.sum(w * (y - p) ** 2) / total) if total > 0 else float("nan")


def pearson(a: np.ndarray, b: np.ndarray, constant: float | None = 0.0) -> float | None:
    """Pearson's r of two equally shaped arrays, all values pooled; ``constant`` when either
    is constant: 0 by default (a field that predicts no change has no correlation with the
    reference's), or None where the score is to be reported as undefined."""
    a, b = np.ravel(a).astype(np.float64), np.ravel(b).astype(np.float64)
    if a.shape != b.shape or a.size < 2:
        raise ValueError(f"a and b must hold the same number (>= 2) of values, got {a.size} and {b.size}")
    if a.std() == 0 or b.std() == 0:
        return constant
    return float(np.corrcoef(a, b)[0, 1])


# --- how strongly a press shows ----------------------------------------------------------------

def contact_strength(images: np.ndarray, no_contact: np.ndarray, regions: np.ndarray) -> np.ndarray:
    """(N,) how strongly each press shows: the mean over its contact region of
    |image - no_contact|, averaged over the channels, in the images' units.

    The project's one measure of a contact's strength: the simulated over the real
    (each against its own no-contact frame, over the same region) is the contact
    strength ratio that ``compare``, the diagnosis and the studies report.

    images : (N, H, W, 3); no_contact : (H, W, 3), or (N, H, W, 3) one per image;
    regions : (N, H, W) bool, or (H, W) for all. A press with an empty region is NaN.
    """
    return contact_contrast(images, no_contact, regions)["change"].mean(axis=1)


def ring_profile(values: np.ndarray, centre_px, bin_px: float, reach_px: float | None = None,
                 min_pixels: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The mean of ``values`` (H, W) over rings ``bin_px`` wide about ``centre_px`` (u =
    column, v = row, pixel centres at integers), out to ``reach_px`` (default: the frame's
    farthest pixel): (each ring's middle radius px, its mean, NaN where it holds fewer than
    ``min_pixels`` pixels, its pixel count)."""
    values = np.asarray(values, np.float64)
    if values.ndim != 2:
        raise ValueError(f"ring_profile: values must be (H, W), got shape {values.shape}")
    if not bin_px > 0:
        raise ValueError(f"ring_profile: bin_px must be > 0, got {bin_px}")
    h, w = values.shape
    v, u = np.mgrid[:h, :w]
    r = np.hypot(u - float(centre_px[0]), v - float(centre_px[1])).ravel()
    reach = float(r.max()) if reach_px is None else float(reach_px)
    keep = (r < reach) & np.isfinite(values.ravel())
    bins = np.floor(r[keep] / bin_px).astype(np.int64)
    n = int(np.ceil(reach / bin_px))
    count = np.bincount(bins, minlength=n)[:n]
    total = np.bincount(bins, values.ravel()[keep], minlength=n)[:n]
    mean = np.where(count >= max(1, min_pixels), total / np.maximum(count, 1), np.nan)
    return (np.arange(n) + 0.5) * bin_px, mean, count


def contact_contrast(images: np.ndarray, no_contact: np.ndarray, regions: np.ndarray) -> dict[str, np.ndarray]:
    """Each press's contact strength (``contact_strength``) in its two factors, per channel:
    ``level`` (N, 3), the no-contact image's mean over the region; ``change`` (N, 3), the
    mean |image - no_contact| there; and ``relative`` (N, 3), change over level.

    A simulator's strength over the real is its level ratio times its relative-change
    ratio: the first is the camera's (exposure, gains, offset, response), the second the
    light's (how strongly the contact changes the light on the paint, less what the
    camera's offset and response dilute). Same arguments as ``contact_strength``; NaN where
    a region is empty or its level is 0."""
    images = np.asarray(images, np.float64)
    if images.ndim != 4 or images.shape[-1] != 3:
        raise ValueError(f"images must be (N, H, W, 3), got shape {images.shape}")
    no_contact = np.broadcast_to(np.asarray(no_contact, np.float64), images.shape) \
        if np.shape(no_contact) == images.shape[1:] else np.asarray(no_contact, np.float64)
    if no_contact.shape != images.shape:
        raise ValueError(f"no_contact must be (H, W, 3) or (N, H, W, 3) like images {images.shape}, got "
                         f"{np.shape(no_contact)}")
    regions = np.broadcast_to(np.asarray(regions, bool), images.shape[:3]) if np.ndim(regions) == 2 \
        else np.asarray(regions, bool)
    if regions.shape != images.shape[:3]:
        raise ValueError(f"regions must be (N, H, W) or (H, W) bool like images {images.shape[:3]}, got "
                         f"{regions.shape}")
    count = regions.sum(axis=(1, 2))[:, None]
    w = regions[..., None]
    with np.errstate(invalid="ignore", divide="ignore"):
        level = np.where(count > 0, (no_contact * w).sum(axis=(1, 2)) / count, np.nan)
        change = np.where(count > 0, (np.abs(images - no_contact) * w).sum(axis=(1, 2)) / count, np.nan)
        relative = np.where(level > 0, change / level, np.nan)
    return {"level": level, "change": change, "relative": relative}


# --- Monte Carlo noise of a render -------------------------------------------------------------

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
    over ``area`` (a bool mask of its pixels): E|e| = sqrt(2 / pi) sigma, averaged."""
    return float(np.sqrt(2 / np.pi) * np.sqrt(np.asarray(variance)[area]).mean())


# --- intervals of a mean over samples ------------------------------------------------------------

def _samples(values, name: str = "values") -> np.ndarray:
    values = np.asarray(values, dtype=np.float64)
    if values.ndim != 1:
        raise ValueError(f"{name} must be one-dimensional (one value per sample), got shape {values.shape}")
    return values


def bootstrap_interval(values, confidence: float = 0.95, resamples: int = 2000, seed: int = 0) -> dict[str, float]:
    """Mean of per-sample values with its percentile-bootstrap interval: {mean, low, high}.

    values : (N,) float, one per sample; samples are resampled as units
    (``scipy.stats.bootstrap``, percentile method: BCa is undefined for two samples),
    seeded by ``seed``. NaN values (a sample whose region was empty) are left out; none
    left gives NaN. One value, or values all equal, give the degenerate interval [mean, mean].
    """
    values = _samples(values)
    if not 0 < confidence < 1:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    values = values[np.isfinite(values)] if np.isnan(values).any() else values
    if len(values) == 0:
        return {"mean": float("nan"), "low": float("nan"), "high": float("nan")}
    mean = float(values.mean())
    if len(values) < 2 or np.ptp(values) == 0:  # every resample gives the same mean
        return {"mean": mean, "low": mean, "high": mean}
    from scipy import stats  # slow to import: only where an interval is drawn

    res = stats.bootstrap((values,), np.mean, confidence_level=confidence, n_resamples=resamples,
                          method="percentile", rng=np.random.default_rng(seed))
    return {"mean": mean, "low": float(res.confidence_interval.low), "high": float(res.confidence_interval.high)}


def t_interval(values, confidence: float = 0.95) -> dict[str, float]:
    """Mean of per-sample values (seeds of a training, say) with Student's t interval:
    {mean, low, high}, mean -+ t_(1+c)/2,N-1 s / sqrt(N) (``scipy.stats.t``). values :
    (N,) float, N >= 1; one value gives the degenerate interval [mean, mean]."""
    values = _samples(values)
    if len(values) == 0:
        raise ValueError("values must hold at least one value, got none")
    if not 0 < confidence < 1:
        raise ValueError(f"confidence must be in (0, 1), got {confidence}")
    mean = float(values.mean())
    if len(values) < 2:
        return {"mean": mean, "low": mean, "high": mean}
    from scipy import stats

    half = float(stats.t.ppf(0.5 + confidence / 2, len(values) - 1) * values.std(ddof=1) / np.sqrt(len(values)))
    return {"mean": mean, "low": mean - half, "high": mean + half}


def percentile_interval(replicates, percents: tuple[float, float] = (5.0, 95.0)) -> list[float]:
    """[low, high]: percentiles of a statistic's bootstrap replicates (N,), for resampling
    that ``scipy.stats.bootstrap`` cannot do (weighted sectors of an image, refits)."""
    replicates = _samples(replicates, "replicates")
    return [float(np.percentile(replicates, percents[0])), float(np.percentile(replicates, percents[1]))]
