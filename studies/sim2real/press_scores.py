"""A localisation's scores: errors with bootstrap intervals, the Real2Real reference and
where the change peaks round a press."""

from __future__ import annotations

import numpy as np

from .locators import SIGMA_PX, CorrelationLocator
from .press_data import Presses

#: Bootstrap resamples of the presses behind the medians' intervals.
RESAMPLES = 4000


def median_ci(values, seed: int = 0) -> dict:
    """The median of per-press values with a 95 % percentile bootstrap interval (presses
    resampled, seeded): {median, low, high}."""
    values = np.asarray(values, np.float64)
    rng = np.random.default_rng(seed)
    draws = np.median(values[rng.integers(0, len(values), (RESAMPLES, len(values)))], axis=1)
    low, high = np.percentile(draws, [2.5, 97.5])
    return {"median": float(np.median(values)), "low": float(low), "high": float(high)}


def errors(model, presses: Presses, pixel_m: float) -> dict:
    """Per press: the localisation error (mm) and the depth error (mm, signed: predicted
    less labelled) of ``model`` on ``presses``; their medians, the localisation's with its
    interval, and its mean."""
    centres, depths = model.predict(presses.differences())
    loc = np.linalg.norm(centres - presses.centres, axis=1) * pixel_m * 1e3
    bias = np.mean(centres - presses.centres, axis=0)
    return {"localisation_mm": loc.tolist(), "depth_error_mm": ((depths - presses.depths) * 1e3).tolist(),
            "localisation_mm_median": float(np.median(loc)), "localisation_mm_median_ci": median_ci(loc),
            "localisation_mm_mean": float(np.mean(loc)),
            "bias_px": bias.tolist(),
            "localisation_mm_median_unbiased": float(np.median(np.linalg.norm(centres - presses.centres - bias, axis=1))
                                                     * pixel_m * 1e3),
            "depth_error_mm_median_abs": float(np.median(np.abs(depths - presses.depths)) * 1e3)}


#: The Real2Real reference's filter: the default width and this ridge, fixed, since the
#: real fitted half it trains on cannot also choose them.
REAL2REAL_RIDGE = 1.0


def real2real(fit_real: Presses, real: Presses, pixel_m: float) -> dict:
    """The filter trained on the capture's real fitted half and tested on its held-out
    presses (``errors``): how consistently the annotations place the presses' own images,
    a floor the simulated trainings are measured against, not a sim-to-real result."""
    model = CorrelationLocator(REAL2REAL_RIDGE, SIGMA_PX).fit(fit_real.differences(), fit_real.centres,
                                                              fit_real.depths)
    return {"sigma_px": SIGMA_PX, "ridge": REAL2REAL_RIDGE, "real": errors(model, real, pixel_m)}


def ring_radii(presses: Presses, ball_radius_px: float) -> np.ndarray:
    """(N,) px: where each press's change, averaged round its labelled centre, peaks
    (``scenes.imports.contact_edge_px``, the import's rim); NaN where no rim is found."""
    from scenes.imports import contact_edge_px

    out = np.full(len(presses.images), np.nan)
    for k in range(len(out)):
        try:
            out[k] = contact_edge_px(presses.images[k], presses.frames[k], presses.centres[k], ball_radius_px)
        except ValueError:
            pass
    return out


def appearance(real: Presses, sim: Presses, ball_radius_px: float) -> dict:
    """How the simulated presses' images differ from the real ones in size: the median
    radius at which each press's change peaks round its centre (``ring_radii``), real and
    simulated, and their ratio (a simulated dent smaller than the real one teaches a
    localiser a template of the wrong size)."""
    r_real, r_sim = ring_radii(real, ball_radius_px), ring_radii(sim, ball_radius_px)
    med_real, med_sim = float(np.nanmedian(r_real)), float(np.nanmedian(r_sim))
    return {"ring_px_real": med_real, "ring_px_sim": med_sim, "sim_over_real": med_sim / med_real,
            "found": {"real": int(np.isfinite(r_real).sum()), "sim": int(np.isfinite(r_sim).sum())}}


def paired(a: dict, b: dict) -> dict:
    """Two trainings' localisation on the same real presses, press by press: the median of
    a - b (mm) with its interval, and the share of presses a localises better."""
    d = np.asarray(a["real"]["localisation_mm"]) - np.asarray(b["real"]["localisation_mm"])
    return {**median_ci(d), "a_better_share": float(np.mean(d < 0))}
