"""Per-pixel agreement of two Monte Carlo images: bounds from their stated variances.

The one home of the z-test that sets the photon estimator beside volpath
(``test_pbr``, ``test_pbr_volpath_contacts``). Each estimate is a mean of independent
passes with a stated variance of that mean (``pbr_tactile.render.Estimate``), so per lit
pixel-channel i the score z_i = (test_i - ref_i) / sqrt(var_test_i + var_ref_i) has a
distribution fixed by those variances, not by what an earlier run gave:

* **Noise.** With Gaussian pass means, z_i is Welch's t with nu_i degrees of freedom
  (Welch-Satterthwaite, from both variances and pass counts): nu = inf gives the
  textbook values, median |z| 0.674 and |z| > 3 on 0.27 % of the values; at the
  passes used here (nu ~ 10 to 60) the tails are heavier (nu = 16: 0.85 %). The pass
  means are not Gaussian but heavy tailed (volpath's rare bright paths; the split
  in-scatter's LEDs seen through the glass, ``pbr_tactile.fluence``), which leaves the
  median alone but loosens the variances read from the passes in the tails: the tail
  share is judged with the fewer passes' nu = passes - 1 for every value, the heaviest
  tail Welch's t can have (nu = 5: 3.0 %, nu = 7: 2.0 %).
* **Bias.** A relative error e of the test estimate shifts z_i by
  delta_i = e ref_i / sigma_i, which makes z_i non-central t (``scipy.stats.nct``).
  The median and the tail share are judged about the common error the aggregate shows
  (clipped to the budget): they test that what is left is the stated noise. The mean and
  the aggregate judge the error itself against ``BIAS_BUDGET``.
* **Correlated values.** The statistics are over n values that are not independent:
  the channels of one pixel share its paths (design effect 1 + (C - 1) rho, rho their
  mean correlation, read from the z's), and neighbouring pixels share the photon map's
  deposits within the kernel's radius r (``pbr_tactile.photons``, module doc: stage 2).
  A pixel whose coating footprint is s wide reads deposits from a square of side
  s + 2 r, that is (1 + 2 r / s)^2 - 1 other footprints; counting each as fully
  correlated in the photon part of the variance (share f) bounds that design effect by
  1 + f ((1 + 2 r / s)^2 - 1). The fluence grid's voxels (``pbr_tactile.fluence``,
  0.5 mm) are smaller than that reach. n_eff is n over both.
* **Sampling.** Each bound is the value a statistic of n_eff independent draws from
  that distribution exceeds with probability ``FALSE_ALARM``: the sample median by the
  binomial count of draws above it, the tail share by the binomial quantile, the mean
  by its normal approximation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import optimize, stats

#: Chance that a statistic of an estimate that agrees (within the budget) breaks its bound.
#: The slow suite makes about 50 such comparisons of 3 distributional statistics each, so
#: a false alarm comes in about one full slow run in seven (1 - (1 - 1e-3)^150 = 0.14).
FALSE_ALARM = 1e-3
#: The |z| whose exceedance share is counted (|z| > 3: 0.27 % for a standard normal).
TAIL_Z = 3.0
#: The photon estimator's accuracy budget against volpath, relative, in aggregate: a
#: requirement, not derived from its output. Its modules state its systematic errors only
#: in order (the density kernel's bias is r^2 times the irradiance's curvature,
#: ``density.irradiance``; the fluence voxel's is its variation across a voxel,
#: ``fluence``). In numbers: for the 2-D Epanechnikov kernel E[u_x^2] = r^2 / 6, so the
#: bias is r^2 (laplacian E) / 12, which at r = 0.75 mm (``render.KERNEL_RADIUS_M``) is 1 %
#: where the irradiance curves over E / |laplacian E| = (2.2 mm)^2 and 6 % at (0.9 mm)^2:
#: the budget lets the kernel blur light that varies over a millimetre, not finer. A change
#: that blurs more or reads the wrong light breaks it: the glossy paint with split camera
#: paths, whose lanes read the lobe from the wrong direction, gives -4.3 to -7.1 % and
#: fails on three of the 8 indenters (docs/layout.md).
BIAS_BUDGET = 0.06
#: Channels of a pixel.
CHANNELS = 3


def pixel_footprint_m(depth_m: float, fov_deg: float, height_px: int) -> float:
    """Width, m, of one pixel's footprint on a surface depth_m ahead, seen square on (a
    slanted surface's footprint is wider, so this is the conservative end)."""
    return depth_m * math.radians(fov_deg) / height_px


@dataclass(frozen=True)
class Agreement:
    """A per-pixel z-test and its bounds. z : (n,) per lit pixel-channel; ratio : the test
    estimate's sum over the reference's; ratio_sigma : its stated standard error."""

    z: np.ndarray
    ratio: float
    ratio_sigma: float
    n_eff: int
    median_bound: float
    tail_bound: float
    mean_bound: float
    expected_median: float
    expected_tail: float

    @property
    def median_abs(self) -> float:
        return float(np.median(np.abs(self.z)))

    @property
    def tail(self) -> float:
        return float(np.mean(np.abs(self.z) > TAIL_Z))

    def summary(self) -> str:
        return (f"per-pixel z over {self.z.size} px (n_eff {self.n_eff}): median |z| {self.median_abs:.2f} "
                f"(expected {self.expected_median:.2f}, bound {self.median_bound:.2f}), mean {self.z.mean():.2f} "
                f"(bound {self.mean_bound:.2f}), |z|>{TAIL_Z:g} {self.tail:.3f} (expected {self.expected_tail:.3f}, "
                f"bound {self.tail_bound:.3f}); aggregate {self.ratio - 1:+.3f} (stated sigma "
                f"{self.ratio_sigma:.3f}, budget {BIAS_BUDGET:g})")

    def check(self, min_values: int = 100) -> None:
        """Assert every statistic within its bound."""
        assert self.z.size > min_values, f"only {self.z.size} lit pixel-channels"
        assert np.isfinite(self.z).all(), "a lit pixel with no stated variance"
        # the budget judges bias, not luck: the aggregate's own noise leaves it room
        assert stats.norm.isf(FALSE_ALARM / 2) * self.ratio_sigma < BIAS_BUDGET, self.summary()
        assert self.median_abs <= self.median_bound, self.summary()
        assert self.tail <= self.tail_bound, self.summary()
        assert abs(self.z.mean()) <= self.mean_bound, self.summary()
        assert abs(self.ratio - 1) <= BIAS_BUDGET, self.summary()


def agreement(test, reference, lit: np.ndarray, footprint_m: float, kernel_radius_m: float | None = None,
              false_alarm: float = FALSE_ALARM) -> Agreement:
    """The z-test of ``test`` against ``reference`` (``Estimate``s: mean and variance
    (H, W, C), passes) over ``lit`` (H, W, C) bool, with bounds from their variances.

    footprint_m : the narrowest coating footprint of one pixel, m (``pixel_footprint_m``);
    kernel_radius_m : the photon density kernel's radius, m (default: the renderer's).
    """
    if kernel_radius_m is None:
        from pbr_tactile.render import KERNEL_RADIUS_M

        kernel_radius_m = KERNEL_RADIUS_M
    for name, est in (("test", test), ("reference", reference)):
        if est.passes < 2:
            raise ValueError(f"{name} must record its passes (>= 2) for its variance's degrees of freedom, "
                             f"got {est.passes}")
    a, b = test.variance[lit].astype(np.float64), reference.variance[lit].astype(np.float64)
    ref = reference.mean[lit].astype(np.float64)
    sigma = np.sqrt(a + b)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = (test.mean[lit] - ref) / sigma
        # Welch-Satterthwaite; a contact's photons (a control variate's difference plus the
        # control's variance, from at least as many passes) are counted at the contact's passes
        nu = np.square(a + b) / (np.square(a) / (test.passes - 1) + np.square(b) / (reference.passes - 1))
        share = a / (a + b)  # the photon (test) estimate's share of each value's variance
    ok = np.isfinite(z) & np.isfinite(nu)
    ratio = float(test.mean[lit].sum() / ref.sum())

    # design effects: the channels of a pixel, then the photon map's kernel across pixels
    full = lit.all(axis=-1)
    per_pixel = ((test.mean - reference.mean) / np.sqrt(test.variance + reference.variance))[full]
    per_pixel = per_pixel[np.isfinite(per_pixel).all(axis=1)]
    if len(per_pixel) > 3:
        c = np.corrcoef(per_pixel.T)
        rho = float(np.clip((c.sum() - np.trace(c)) / (c.size - len(c)), 0.0, 1.0))
    else:
        rho = 1.0
    reach = (1 + 2 * kernel_radius_m / footprint_m) ** 2 - 1
    design = (1 + (CHANNELS - 1) * rho) * (1 + float(np.mean(share[ok])) * reach)
    n_eff = max(1, int(ok.sum() / design))

    nu, ref_ok, sigma_ok = nu[ok], ref[ok], sigma[ok]
    shift = np.clip(ratio - 1, -BIAS_BUDGET, BIAS_BUDGET) * ref_ok / sigma_ok

    def exceed(m):  # P(|z| > m) for a value drawn from the null's mixture
        return float(np.mean(stats.nct.sf(m, nu, shift) + stats.nct.cdf(-m, nu, shift)))

    top = 50.0 + float(np.max(np.abs(shift)))  # past every value's centre: exceed(top) ~ 0
    expected_median = optimize.brentq(lambda m: exceed(m) - 0.5, 1e-6, top)
    half = n_eff // 2 + 1  # the sample median is above m when more than half the draws are
    median_bound = optimize.brentq(lambda m: stats.binom.sf(half - 1, n_eff, exceed(m)) - false_alarm, 1e-6, top)
    # the tail share with the fewer passes' degrees of freedom for every value: the pass
    # means are heavy tailed, so the variances read from them are loosest in the tails
    heavy = min(test.passes, reference.passes) - 1
    expected_tail = float(np.mean(stats.nct.sf(TAIL_Z, heavy, shift) + stats.nct.cdf(-TAIL_Z, heavy, shift)))
    tail_bound = float(stats.binom.isf(false_alarm, n_eff, expected_tail)) / n_eff

    budget = BIAS_BUDGET * ref_ok / sigma_ok  # the budget in noise units, per value
    mean_bound = float(np.mean(stats.nct.mean(nu, budget))
                       + stats.norm.isf(false_alarm / 2) * math.sqrt(np.mean(stats.nct.var(nu, budget)) / n_eff))
    ratio_sigma = float(math.sqrt(design * np.sum((a + b)[ok])) / ref.sum())
    return Agreement(np.asarray(z, np.float64), ratio, ratio_sigma, n_eff, float(median_bound), tail_bound,
                     mean_bound, float(expected_median), float(expected_tail))
