"""The fit of an image model (``pbr_tactile.image_model``) to a real image and its taps:
the nonlinear parameters searched by bounded least squares from several rotations, the
gains solved for each (variable projection), the fit's covariance, and its loss less the
basis' own Monte Carlo noise (``debiased``).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
from scipy import optimize

from .image_model import ImageModel, Nonlinear, solve_gains, solve_spectral_gains
from .real_image import CLIP_LEVEL

#: Starting rotations of the search (the LEDs repeat every 120 deg but their colours do not).
ROTATION_STARTS = 12
#: Function evaluations (least-squares steps; the Jacobian's finite differences are not
#: counted) every start takes before the best are refined: the losses at the starts
#: themselves barely differ (each LED lights the membrane nearly all round), and ranked
#: by them the search kept two wrong basins of a blind sensor's image and stopped at
#: 1.6e-4 where its truth gives 0 (its own basis, no noise); after 6 steps the true basin
#: ranked first.
SCREEN_EVALUATIONS = 6
#: A fit has converged when Powell's method says so and it either moved off its start
#: (the loss fell by this share) or already leaves less than STUCK_SHARE of the real
#: image's variance: a fit that leaves a large gap without moving stopped at its start.
MIN_IMPROVEMENT = 1e-3
STUCK_SHARE = 0.05


@dataclass
class ImageFit:
    """A fitted image model: nonlinear parameters, gains (L, 3), offset (3,), loss."""

    nl: Nonlinear
    gains: np.ndarray
    offset: np.ndarray
    loss: float
    start_loss: float
    converged: bool
    evaluations: int
    #: the part of ``loss`` the basis' Monte Carlo noise is expected to add (``_debiased``)
    noise: float = 0.0


@dataclass
class TapView:
    """One tap in a fit: its per-source change from the no-contact basis (h, w, S; see
    ImageModel.tap_design) with the LEDs where the spec has them, the real tap image (h,
    w, 3), the pixels it is fitted on (h, w) and its weight (a bootstrap's multiplicity).
    ``slope`` and ``curve`` (h, w, S), where given, make the change depend on each LED's
    azimuth a: change + a slope + a^2 curve (``pbr_tactile.calibrate_taps``)."""

    change: np.ndarray
    real: np.ndarray
    pixels: np.ndarray
    weight: float = 1.0
    slope: np.ndarray | None = None
    curve: np.ndarray | None = None

    def at(self, nl: Nonlinear, led: np.ndarray) -> np.ndarray:
        """(h, w, S) the change with the LEDs at ``nl``'s azimuths; ``led`` (S,) each
        source's LED."""
        if self.slope is None:
            return self.change
        a = np.asarray(nl.led_azimuth_rad, np.float64)[led]
        return self.change + a * self.slope + a * a * self.curve


class ImageFitter:
    """Fits an ImageModel to a real image on a set of pixels, and to taps if given (see
    the module doc and ``pbr_tactile.calibrate_taps``)."""

    def __init__(self, model: ImageModel, real: np.ndarray, fit_pixels: np.ndarray, weight: np.ndarray | None = None,
                 leak: bool = True, taps: list[TapView] = (), common_turn: bool = False):
        """fit_pixels (h, w) bool; weight (h, w) per-pixel weights (a bootstrap's
        multiplicities) or None; leak False: no light into the core (the leak fixed at 0);
        taps: fitted together with the image, their pixels stacked with its;
        common_turn: the LEDs' azimuths tied to one value, the ring's turn against the
        membrane (see NOT_IDENTIFIABLE_WITH_TAPS)."""
        self.model, self.real = model, np.asarray(real, np.float64)
        self.leak = leak
        self.common_turn = common_turn
        self.pixels = fit_pixels & model.inside
        self.clipped = self.real >= CLIP_LEVEL
        self.weight = None if weight is None else np.asarray(weight, np.float64)[self.pixels]
        self.taps = [t for t in taps if t.weight > 0]
        # the stacked real pixels, censoring and weights of the image and the taps
        views = [(self.real, self.pixels, np.ones(int(self.pixels.sum())) if weight is None else self.weight)]
        views += [(np.asarray(t.real, np.float64), t.pixels & model.inside,
                   np.full(int((t.pixels & model.inside).sum()), float(t.weight))) for t in self.taps]
        self.y = np.concatenate([real_[pixels] for real_, pixels, _ in views])
        self.y_clipped = self.y >= CLIP_LEVEL
        self.w = np.concatenate([w for _, _, w in views])
        # the loss of predicting each channel's mean: the real image's variance
        self.variance = float(np.mean([np.var(self.real[..., c][self.pixels]) for c in range(3)]))

    def design(self, nl: Nonlinear) -> np.ndarray:
        """(N, L) the stacked design rows of the image's and the taps' fitted pixels."""
        falloff = self.model.falloff(nl)[..., None]
        warped = self.model.warped(nl)
        rows = [(warped * falloff)[self.pixels]]
        for t in self.taps:
            change = self.model._mixed(t.at(nl, self.model.led), nl, 1, azimuths=False)
            rows.append(((warped + change) * falloff)[t.pixels & self.model.inside])
        return np.concatenate(rows)

    def solve(self, nl: Nonlinear) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The best gains and offsets for ``nl`` and the weighted, censored residuals,
        whose sum of squares is the mean squared error over pixels and channels."""
        X = self.design(nl)
        w = self.w
        sw = np.sqrt(w / (3 * np.sum(w)))
        weight = None if self.weight is None and not self.taps else w
        if self.model.response is not None:
            gains, offset = solve_spectral_gains(X, self.y, self.y_clipped, nl.gamma, self.model.response, weight,
                                                 black=self.model.black)
        else:
            gains, offset = np.zeros((self.model.leds, 3)), np.zeros(3)
            for c in range(3):
                gains[:, c], offset[c] = solve_gains(X, self.y[:, c], self.y_clipped[:, c], nl.gamma, weight,
                                                     black=self.model.black)
        residuals = []
        for c in range(3):
            y, clipped = self.y[:, c], self.y_clipped[:, c]
            pred = np.clip(X @ gains[:, c] + offset[c], 0.0, None) ** (1.0 / nl.gamma)
            residuals.append(sw * np.where(clipped, np.minimum(pred - y, 0.0), pred - y))
        return gains, offset, np.concatenate(residuals)

    def loss(self, z: np.ndarray) -> float:
        """The censored mean squared error at nonlinear parameters ``z``."""
        return float(np.sum(self.solve(self.model.nonlinear(z))[2] ** 2))

    def fit(self, start: Nonlinear, max_evaluations: int = 1500, start_loss: float | None = None) -> ImageFit:
        """Bounded least squares over the nonlinear parameters from ``start`` (the gains
        solved inside every evaluation: variable projection). ``start_loss``: the loss the
        search began from, where ``start`` is already part of the way (the convergence
        test asks whether the fit moved from there)."""
        leds = self.model.leds
        bounds = np.array(self.model.bounds(self.leak and self.model.has_leak.any()))
        free = bounds[:, 1] > bounds[:, 0]
        z0 = np.clip(start.vector(), bounds[:, 0], bounds[:, 1])
        if self.common_turn:
            # the first LED's azimuth is searched, the others follow it
            z0[1:1 + leds] = np.mean(z0[1:1 + leds])
            free[2:1 + leds] = False
        start_loss = self.loss(z0) if start_loss is None else start_loss

        def full(zf):
            z = z0.copy()
            z[free] = zf
            if self.common_turn:
                z[2:1 + leds] = z[1]
            return z

        def residuals(zf):
            return self.solve(self.model.nonlinear(full(zf)))[2]

        result = optimize.least_squares(residuals, z0[free], bounds=(bounds[free, 0], bounds[free, 1]),
                                        diff_step=1e-3, max_nfev=max_evaluations, x_scale="jac")
        z = full(result.x)
        nl = self.model.nonlinear(z)
        gains, offset, res = self.solve(nl)
        loss = float(np.sum(res**2))
        moved = loss < start_loss * (1 - MIN_IMPROVEMENT)
        small = loss <= STUCK_SHARE * self.variance
        return ImageFit(nl, gains, offset, loss, start_loss, result.status > 0 and (moved or small), int(result.nfev))

    def covariance(self, nl: Nonlinear, variance: np.ndarray, step: float = 1e-3) -> np.ndarray:
        """(P, P) the searched coordinates' covariance (``Nonlinear.vector``'s order; 0 for
        those the search holds) at ``nl`` that noise of per-pixel ``variance`` (h, w, 3) in
        the fitted image causes, to first order: the sandwich (J'J)^+ J'SJ (J'J)^+ of the
        residuals' Jacobian J (central differences, the gains solved at each: variable
        projection) with S the residuals' variances. The pseudo-inverse leaves out what
        the image does not see (the rotation against the LEDs' mean azimuth): only
        combinations it sees (``tied_errors``) are meaningful there. Without taps only."""
        if self.taps:
            raise ValueError("covariance: a fit with taps is not covered")
        bounds = np.array(self.model.bounds(self.leak and self.model.has_leak.any()))
        free = np.nonzero(bounds[:, 1] > bounds[:, 0])[0]
        z = nl.vector()
        columns = []
        for i in free:
            h = step * max(1.0, abs(z[i]))
            up, down = z.copy(), z.copy()
            up[i], down[i] = z[i] + h, z[i] - h
            rise = self.solve(self.model.nonlinear(up))[2] - self.solve(self.model.nonlinear(down))[2]
            columns.append(rise / (2 * h))
        J = np.stack(columns, axis=1)
        share = self.w / (3 * np.sum(self.w))  # each residual is sqrt(share) times an error (``solve``)
        S = np.concatenate([share * np.asarray(variance, np.float64)[..., c][self.pixels] for c in range(3)])
        inverse = np.linalg.pinv(J.T @ J)
        out = np.zeros((len(z), len(z)))
        out[np.ix_(free, free)] = inverse @ (J.T * S) @ J @ inverse
        return out

    def search(self, rotations: int = ROTATION_STARTS, max_evaluations: int = 2000, keep: int = 2,
               screen: int = SCREEN_EVALUATIONS) -> ImageFit:
        """Fit from ``rotations`` evenly spaced starting rotations: each start ``screen``
        evaluations first (SCREEN_EVALUATIONS; 0: each start's gains alone), then the
        ``keep`` best refined in full."""
        leak = 0.3 if self.leak and self.model.has_leak.any() else 0.0
        rotations = 1 if self.model.known_alignment else rotations
        starts = [self.model.start(2 * math.pi * k / rotations, leak) for k in range(rotations)]
        if screen <= 0:
            screened = [(nl, None) for nl in sorted(starts, key=lambda nl: self.loss(nl.vector()))[:keep]]
        else:
            ahead = sorted((self.fit(nl, screen) for nl in starts), key=lambda f: f.loss)[:keep]
            screened = [(f.nl, f.start_loss) for f in ahead]
        fits = [self.fit(nl, max_evaluations, start_loss) for nl, start_loss in screened]
        return min(fits, key=lambda f: f.loss)


def tied_errors(nl: Nonlinear, cov: np.ndarray) -> dict[str, float]:
    """Standard errors (``ImageFitter.covariance``) of what one image sees: the tied
    rotation (the rotation plus the LEDs' mean azimuth, ``Nonlinear.tied``) and every
    other searched coordinate but the azimuths; 0-variance (held) ones left out."""
    names = nl.names()
    n = len(nl.led_azimuth_rad)
    tie = np.zeros(len(names))
    tie[0], tie[1:1 + n] = 1.0, 1.0 / n
    out = {"rotation_rad": float(np.sqrt(max(tie @ cov @ tie, 0.0)))}
    for i, name in enumerate(names):
        if i > n and cov[i, i] > 0:
            out[name] = float(np.sqrt(cov[i, i]))
    return out


def debiased(fit: ImageFit, model: ImageModel, basis: dict, pixels: list[np.ndarray]) -> ImageFit:
    """The fit with ``noise``: the part of its loss the basis' own Monte Carlo noise
    adds, the mean prediction variance over the fitted pixels (``pixels``: the image's,
    then each tap's, where the no-contact basis' variance stands for the tap's). Grid
    points are compared by loss - noise: a basis rendered with strong absorption and
    scattering is noisier (fewer photons reach most of the membrane), and its raw loss
    ranked a blind sensor's own point last of nine."""
    var = model.prediction_variance(basis["variance"], fit.nl, fit.gains)
    noise = float(np.mean(np.concatenate([var[m & model.inside] for m in pixels])))
    return dataclasses.replace(fit, noise=noise)
