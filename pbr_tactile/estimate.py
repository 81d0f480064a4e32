"""Monte Carlo images in independent passes: the mean, the variance of that mean, and its noise.

Both estimators of the reference (``pbr_tactile.render``: volpath and the photon
estimator) run the one pass loop here (``run_passes``): a fixed number of independent
passes, or passes until the noise over the contact region (``contact_rse`` over
``contact_region``) meets a target. Each pass is one image; the ``Estimate`` is their mean
and the variance of that mean, optionally against the no-contact frame as a control
variate (``Control``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from scenes.camera import CONTACT_EPS_M, Camera, pinhole_view


#: Fewest passes of any estimate: the variance across passes needs two.
MIN_PASSES = 2
#: Default cap on the passes of a render that stops on a noise target.
MAX_PASSES = 16
#: The contact region reaches this far beyond the pixels whose depth changed, px at the
#: camera's resolution: the dent's rim, where the elastic layer bends, counts too.
RIM_PX = 8


@dataclass(frozen=True)
class Control:
    """An image-level control variate: the no-contact frame, pass by pass.

    images : (K, H, W, 3) the frame's pass k rendered with pass k's random numbers (the
        same seed a contact's pass k uses); mean : (H, W, 3) an unbiased estimate of
        each image's expectation, more precise than their average (more camera samples);
        variance : (H, W, 3) the variance of that mean. Linear, before sensor effects.

    A contact's pass k, minus ``images[k]``, plus ``mean``, is unbiased for the contact's
    image; where the contact does not change a path (every path far from the dent, and
    the LEDs seen through the glass, a rare and bright camera sample) the two passes
    share its value and it cancels (``run_passes``).
    """

    images: np.ndarray
    mean: np.ndarray
    variance: np.ndarray

    def __post_init__(self):
        images, mean, variance = (np.asarray(a) for a in (self.images, self.mean, self.variance))
        if images.ndim != 4 or mean.shape != images.shape[1:] or variance.shape != mean.shape:
            raise ValueError(f"a Control needs images (K, H, W, C) and mean and variance (H, W, C), got "
                             f"{images.shape}, {mean.shape} and {variance.shape}")


@dataclass(frozen=True)
class Estimate:
    """A Monte Carlo image: mean (H, W, 3) float32 linear, and the variance of that mean.

    spp : samples per pixel in all; passes : the independent passes averaged (0: not
    recorded); rse : the RMS relative standard error (``contact_rse``) over the region a
    noise target was judged on, None when the number of passes was fixed; control : this
    estimate as a control for contacts rendered with its seeds (``Control``, before
    sensor effects), where it was asked for.
    """

    mean: np.ndarray
    variance: np.ndarray
    spp: int
    passes: int = 0
    rse: float | None = None
    control: Control | None = None

    @classmethod
    def from_passes(cls, images: list[np.ndarray], spp: int) -> Estimate:
        """Mean of independent pass images and the variance of that mean; spp in all."""
        stack = np.stack(images)
        return cls(stack.mean(axis=0).astype(np.float32),
                   (stack.var(axis=0, ddof=1) / len(images)).astype(np.float32), spp, len(images))

    @property
    def relative_error(self) -> np.ndarray:
        """Per-pixel standard error over the mean (inf where the mean is 0)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.sqrt(self.variance) / self.mean


def contact_rse(est: Estimate, region: np.ndarray | None = None) -> float:
    """Root-mean-square relative standard error over the region's lit pixels.

    region : (H, W) bool, None: the whole image. Pixels (and channels) with a zero mean
    are left out; nan when none is left.

    The per-pixel variance across passes is unbiased, so its mean over the region is
    too; its square root is not (with 2 passes the mean of per-pixel standard errors
    reads 0.8 of the truth, which would flatter the time to target by 1.6x). The root of
    the mean relative variance is what is reported: the RMS of the per-pixel RSE.
    """
    variance, mean = (est.variance, est.mean) if region is None else (est.variance[region], est.mean[region])
    with np.errstate(divide="ignore", invalid="ignore"):
        rel_var = variance / np.square(mean)
    rel_var = rel_var[np.isfinite(rel_var)]
    return float(np.sqrt(np.mean(rel_var))) if rel_var.size else float("nan")


def contact_region(depth: np.ndarray | None, ref_depth: np.ndarray | None, camera: Camera,
                   width: int | None = None, height: int | None = None) -> np.ndarray:
    """The pixels a contact's noise is judged on, at the film's resolution.

    depth, ref_depth : (H, W) float, metres, planar z at the camera's resolution (depth
    None: no contact). Returns (height, width) bool: the pixels whose depth differs from
    D_ref by more than CONTACT_EPS_M, grown by RIM_PX (camera pixels) so the dent's rim
    counts, inside the image circle; the whole image circle without contact, or when the
    contact lies outside it.
    """
    from scipy import ndimage

    width, height = width or camera.width, height or camera.height
    lens = camera.scaled(width, height)
    cover = lens.pinhole_cover()  # what the film is (sensor_effects)

    def on_film(mask):
        return mask if cover is lens else pinhole_view(mask, lens, cover)

    circle = lens.mask
    if depth is None:
        return on_film(circle.copy())
    moved = np.abs(np.asarray(depth, np.float64) - ref_depth) > CONTACT_EPS_M
    if moved.any():
        moved = ndimage.binary_dilation(moved, iterations=RIM_PX)
    # Each film pixel reads the camera pixel nearest its centre (the rim spans 2 RIM_PX
    # camera pixels, so films down to 1/16 of the camera's size cannot miss a contact).
    rows = np.clip(np.round((np.arange(height) + 0.5) * camera.height / height - 0.5).astype(int), 0, camera.height - 1)
    cols = np.clip(np.round((np.arange(width) + 0.5) * camera.width / width - 0.5).astype(int), 0, camera.width - 1)
    region = moved[np.ix_(rows, cols)] & circle
    return on_film(region if region.any() else circle.copy())


def check_passes(passes: int, target_rse: float | None = None, max_passes: int = MAX_PASSES) -> None:
    """Validate a pass count (fixed, or the fewest with a target) and a noise target."""
    if passes < MIN_PASSES:
        raise ValueError(f"passes must be >= {MIN_PASSES} for a variance estimate, got {passes}")
    if target_rse is None:
        return
    if not (isinstance(target_rse, (int, float)) and math.isfinite(target_rse) and target_rse > 0):
        raise ValueError(f"target_rse must be a finite number > 0 (a relative standard error, e.g. 0.05), "
                         f"got {target_rse!r}")
    if max_passes < passes:
        raise ValueError(f"max_passes must be >= passes ({passes}), got {max_passes}")


def run_passes(one_pass, spp: int, passes: int = 4, target_rse: float | None = None,
               region: np.ndarray | None = None, max_passes: int = MAX_PASSES, progress=None,
               control: Control | None = None) -> Estimate:
    """The one pass loop of both estimators: independent passes, averaged.

    one_pass : k -> (H, W, 3) image of pass k (independent random numbers per k).
    spp : samples per pixel of one pass.
    passes : how many passes (target_rse None), else the fewest (>= MIN_PASSES).
    target_rse : stop after the first pass at which the RMS relative standard error
        over ``region`` (``contact_rse``) is at most this, or after ``max_passes``. The
        error falls as 1/sqrt(passes). Stopping on an estimated error slightly favours
        passes whose estimate came out low; averaged over a region of many pixels that
        estimate is steady enough for the bias to be small.
    progress : called with (passes done, most passes) after each pass.
    control : a ``Control`` whose ``images[k]`` shares pass k's random numbers: the
        estimate is then mean_k(pass_k - images[k]) + control.mean, its variance
        var_k(pass_k - images[k]) / passes + control.variance. Unbiased whatever the
        correlation; it pays where the two share most of their paths. Its images must
        cover every pass that may run.

    Returns the Estimate; with a target, its ``rse`` is the error it stopped at.
    """
    check_passes(passes, target_rse, max_passes)
    most = passes if target_rse is None else max_passes
    if control is not None and len(control.images) < most:
        raise ValueError(f"the control has {len(control.images)} pass images but up to {most} passes may run")

    def estimate() -> Estimate:
        est = Estimate.from_passes(images, spp * len(images))
        if control is None:
            return est
        return replace(est, mean=(est.mean + control.mean).astype(np.float32),
                       variance=(est.variance + control.variance).astype(np.float32))

    images = []
    for k in range(most):
        image = one_pass(k)
        images.append(image if control is None else image - control.images[k])
        if progress is not None:
            progress(k + 1, most)
        if target_rse is not None and k + 1 >= passes:
            est = estimate()
            rse = contact_rse(est, region)
            if rse <= target_rse:
                break
    if target_rse is None:
        return estimate()
    return replace(est, rse=rse)
