"""Where a fit starts: each candidate effect's starting points (``studies.gap.fit``
refines the best of them), closed-form where the effect is linear in its parameters for a
fixed exponent (the colour matrix per gamma, the log fall-off's and the fade's optical
depths), registration and a coarse search for shifts and turns, small grids where the loss
has several basins. Each function reads the training frames of a ``fit.Fitter``.
"""

from __future__ import annotations

import numpy as np
from scipy import optimize
from skimage.registration import phase_cross_correlation

from . import effects as fx

#: Gammas at which a closed-form colour matrix starts camera_response fits.
START_GAMMAS = (0.5, 0.6, 0.7, 0.8, 0.9, 1.0, 1.15, 1.3, 1.5, 1.75, 2.0, 2.5)
#: path_attenuation: closed-form starts at these shares of the axial distance, and a
#: Beer-Lambert start (every stretch's optical depth alike) at each of these depths.
FADE_START_SHARES = (0.0, 0.5, 1.0)
FADE_UNIFORM_STARTS = (0.1, 0.3, 0.6, 1.0)
#: path_attenuation's closed form bins the training pixels by distance into this many
#: bins and fits each bin's median log ratio (the median: the fitted loss is an MAE).
FADE_BINS = 120
#: Weight of the pull of camera_response's closed-form colour matrix towards the white
#: balance, relative to the mean diagonal of its normal equations.
RESPONSE_RIDGE = 3e-3


def starts(fitter, name: str) -> list[dict]:
    """Starting points of one effect's fit (the best of them is refined)."""
    effect = fitter.catalogue[name]
    base = dict(effect.identity)
    own = name
    if fitter.work.kind != "fast":
        if name not in fitter.work.aliases:
            return fitter.work.starts(name)
        name = fitter.work.aliases[name]  # a fast image model under the model's own name
    # Start just off the identity where the identity is a flat spot of the loss.
    nudges = {"core_light_leak": {k: 0.1 for k in base if k.startswith("amplitude")},
              "coating_gloss": {"k_g": 0.2},
              "contact_shadow": {"darkness": 0.5},
              "blur_noise": {"sigma_px": 1.0}}
    base.update(nudges.get(name, {}))
    if name == "misalignment":
        return _misalignment_starts(fitter, base, effect.name)
    if name == "path_attenuation":
        return _fade_starts(fitter, base)
    if name == "lens_distortion":
        return [{**base, "k1": k} for k in (-0.2, -0.1, 0.0, 0.1, 0.2)]
    if name == "membrane_compliance":
        return [{**base, "scale": s} for s in (0.5, 0.8, 1.1)]
    if name == "elastic_spread":
        sigma = base["sigma_px"]
        return [{**base, "sigma_px": sigma * k} for k in (0.5, 0.8, 1.25, 1.8)]
    if name == "contact_shadow":
        return [{**base, "elevation_rad": e} for e in (0.1, 0.3, 0.6)]
    if name == "coating_gloss":
        return [{**base, "shininess": s} for s in (8.0, 30.0, 100.0)]
    if name == "camera_response":
        return _response_starts(fitter, base, own)
    if name == "vignetting":
        return [base, _vignetting_start(fitter, base)]
    return [base]

def _pixels(fitter) -> tuple[np.ndarray, np.ndarray]:
    """(K, 3) simulated and real training colours inside the circle, where neither is
    clipped (the closed-form starts' data)."""
    inside = np.broadcast_to(fitter.box_mask[..., 0] > 0, fitter.box_mask.shape[:-1])
    rows, cols = fitter.box
    sim, real = fitter.sim_w[:, rows, cols][inside], fitter.real_w[:, rows, cols][inside]
    keep = (sim.max(axis=1) < 0.99) & (real.max(axis=1) < 0.99) & (sim.min(axis=1) > 0.004)
    return sim[keep].astype(np.float64), real[keep].astype(np.float64)

def _response_starts(fitter, base: dict, effect: str = "camera_response") -> list[dict]:
    """Per gamma of ``START_GAMMAS``, the colour matrix and offset in closed form: out =
    (C in + o)^(1/gamma) makes real^gamma = C sim + o, linear in C and o, solved by
    least squares over the training pixels; and the white balance alone (C diagonal,
    o = 0), g_c = sum(s_c r_c^gamma) / sum(s_c^2). The full solution is pulled weakly
    (``RESPONSE_RIDGE``) towards the white balance, so that where the colours hardly
    vary (a solid background) the entries they cannot pin stay there."""
    sim, real = _pixels(fitter)
    if len(sim) < 16:
        return [{**base, "gamma": g} for g in (0.7, 1.0, 1.4)]
    bounds = {p.name: (p.low, p.high) for p in fitter.catalogue[effect].params}
    # Normal equations of real_c^gamma = sim . C_c + o over the three channels at once:
    # unknowns (C_r, C_g, C_b, o), 10 of them.
    S = sim.T @ sim  # (3, 3)
    s = sim.sum(axis=0)  # (3,)
    A = np.zeros((10, 10))
    for c in range(3):
        A[3 * c:3 * c + 3, 3 * c:3 * c + 3] = S
        A[3 * c:3 * c + 3, 9] = A[9, 3 * c:3 * c + 3] = s
    A[9, 9] = 3 * len(sim)
    ridge = RESPONSE_RIDGE * np.trace(A) / len(A)
    out = []
    for gamma in START_GAMMAS:
        target = real**gamma  # (K, 3)
        b = np.concatenate([sim.T @ target[:, c] for c in range(3)] + [[target.sum()]])
        gains = (sim * target).sum(axis=0) / np.maximum((sim * sim).sum(axis=0), 1e-12)
        diagonal = np.diag(gains)
        prior = np.append(diagonal.reshape(-1), 0.0)
        x = np.linalg.solve(A + ridge * np.eye(len(A)), b + ridge * prior)
        for matrix, offset in ((x[:9].reshape(3, 3), x[9]), (diagonal, 0.0)):
            start = {**base, "gamma": gamma, "offset": float(np.clip(offset, *bounds["offset"]))}
            for o, co in enumerate(fx.CHANNELS):
                for i, ci in enumerate(fx.CHANNELS):
                    name = f"gain_{co}" if o == i else f"mix_{co}{ci}"
                    start[name] = float(np.clip(matrix[o, i], *bounds[name]))
            out.append(start)
    return out

def _fade_starts(fitter, base: dict) -> list[dict]:
    """path_attenuation's starts. In closed form per share of the axial distance
    (``FADE_START_SHARES``): where every light fades alike, log(real / sim) = -tau(d)
    is linear in the stretches' optical depths (``_log_profile`` over the background's
    distance), then the same depths on the LEDs' own terms alone and on the background
    alone; and Beer-Lambert ones, every stretch alike (``FADE_UNIFORM_STARTS``), along
    the membrane and along the axis, of every light and of the LEDs' own terms alone."""
    model = fitter.work
    knots, most = fx.FADE_KNOTS, fx.FADE_DEPTH_MAX
    rows, cols = fitter.box

    def start(depths, share: float, led: float = 1.0, ambient: float = 1.0) -> dict:
        return {**base, **{f"depth_{k}": float(v) for k, v in enumerate(depths)}, "axial_share": share,
                "led_weight": led, "ambient_weight": ambient}

    out = [start([d] * knots, s, ambient=a) for d in FADE_UNIFORM_STARTS for s in (0.0, 1.0) for a in (0.0, 1.0)]
    for share in FADE_START_SHARES:
        d = fx.fade_distances(model.base_distance, model.axial, share)[rows, cols]
        solved = _log_profile(fitter, d, model.fade_length, knots, most)
        if solved is None:
            break
        out += [start(solved, share), start(solved, share, ambient=0.0), start(solved, share, led=0.0)]
    return out

def _vignetting_start(fitter, base: dict) -> dict:
    """The log fall-off's stretches in closed form about the image centre: real = sim V
    makes log(real / sim) = -sum_k depth_k ramp_k(r), solved with the depths >= 0 over
    the median log ratio of the training pixels in bins of r (``_log_profile``)."""
    camera = fitter.work.camera
    rows, cols = fitter.box
    r = fx.radial_distance(camera.shape, camera.f, (camera.cy, camera.cx))[rows, cols]
    length = fx.vignette_length(camera.mask, camera.f, fitter.work.factor)
    depths = _log_profile(fitter, r, length, fx.VIGNETTE_KNOTS, fx.VIGNETTE_DEPTH_MAX)
    if depths is None:
        return base
    return {**base, **{f"depth_{k}": float(v) for k, v in enumerate(depths)}}

def _log_profile(fitter, distance: np.ndarray, length: float, knots: int, most: float) -> np.ndarray | None:
    """(knots,) optical depths >= 0 (at most ``most``) of the profile exp(-tau(d)) that
    takes the simulated training pixels to the real ones, tau piecewise linear in the
    distance over ``knots`` equal stretches of [0, length] (``effects.fade_ramps``):
    least squares (scipy's lsq_linear) over the median log(real / sim), mean over the
    channels, of the unclipped pixels of the circle in each of ``FADE_BINS`` bins of
    the distance (the median: the fitted loss is an MAE). ``distance`` (h, w) over the
    fit's box, or (N, h, w). None when under 16 pixels are usable."""
    rows, cols = fitter.box
    inside = fitter.box_mask[..., 0] > 0
    sim = fitter.sim_w[:, rows, cols].mean(axis=-1)
    real = fitter.real_w[:, rows, cols].mean(axis=-1)
    keep = inside & (sim > 0.02) & (real > 0.02) & (sim < 0.99) & (real < 0.99)
    if keep.sum() < 16:
        return None
    ratio = np.log(real[keep]) - np.log(sim[keep])
    d = np.broadcast_to(distance, keep.shape)[keep] / length
    bins = np.clip((d * FADE_BINS).astype(int), 0, FADE_BINS - 1)
    order = np.argsort(bins, kind="stable")
    edges = np.searchsorted(bins[order], np.arange(FADE_BINS + 1))
    filled = [(edges[b], edges[b + 1]) for b in range(FADE_BINS) if edges[b + 1] > edges[b]]
    centres = np.array([np.median(d[order[a:z]]) for a, z in filled])
    target = np.array([-np.median(ratio[order[a:z]]) for a, z in filled])
    weight = np.sqrt([z - a for a, z in filled])
    A = fx.fade_ramps(centres * length, length, knots).T.astype(np.float64)
    return optimize.lsq_linear(A * weight[:, None], target * weight, bounds=(0.0, most)).x

def _misalignment_starts(fitter, base: dict, name: str = "misalignment") -> list[dict]:
    """The registrations' moves first (``registrations``: in closed form, a reliable
    one of each kind; an unreliable one starts from zero), then the best four of a
    search: rotation from a coarse grid (every 10 degrees, then 1 degree around the
    best) and shift by phase correlation, both on the mean images of the fitting
    samples (one image, so the search is cheap), for the membrane moving under a fixed
    image circle and for the whole frame moving (``frame_share`` 0 and 1). ``fit``
    refines the best of them on every sample.

    Registration compares what moves. Under a fixed circle that is what the
    simulated background does not explain (image - ``FastModel.fixed``), so that a
    real no-contact background, registered already, does not pin the search at the
    identity; when the whole frame moves it is the whole image, background included
    (subtracting the fixed background from both would leave the same unmoved pattern
    in each, and pin the shift at 0)."""
    fixed = fitter.work.fixed
    real = fitter.real_w.mean(axis=0)
    sim = fitter.sim_w.mean(axis=0)[None]
    limit = next(p.high for p in fitter.catalogue[name].params if p.name == "du_px") - 1.0  # px, inside the bounds
    shares = (0.0, 1.0) if "frame_share" in base else (1.0,)
    closed = list(fitter.closed_moves(base, name).values())

    def registered(angle: float, share: float) -> tuple[float, dict]:
        params = {**base, "rotation_rad": float(angle), "du_px": 0.0, "dv_px": 0.0}
        if "frame_share" in base:
            params["frame_share"] = share
        rotated = fitter.work.optics(sim, {name: params})[0]
        moving = fixed if share < 1.0 else 0.0
        shift, _, _ = phase_cross_correlation((real - moving).mean(-1), (rotated - moving).mean(-1),
                                              upsample_factor=4, normalization=None)
        # Real ~ the rotated image moved by ``shift`` (rows, cols), working pixels. The
        # model samples the simulated frame at c + R (x - c) + (du, dv), full-resolution
        # pixels: the rotated image at x + R^-1 (du, dv), so (du, dv) = -R shift.
        c, s = np.cos(angle), np.sin(angle)
        x, y = -shift[1] * fitter.work.factor, -shift[0] * fitter.work.factor
        du, dv = (float(np.clip(v, -limit, limit)) for v in (c * x - s * y, s * x + c * y))
        params.update(du_px=du, dv_px=dv)
        pred = fitter.work.optics(sim, {name: params})[0]
        return float(np.mean(np.abs(pred - real)[fitter.mask_w])), params

    found = []
    for share in shares:
        coarse = [registered(a, share) for a in np.deg2rad(np.arange(-180, 180, 10))]
        best = min(coarse, key=lambda t: t[0])[1]["rotation_rad"]
        found += coarse + [registered(best + a, share) for a in np.deg2rad(np.arange(-4, 5, 1))]
    return closed + [p for _, p in sorted(found, key=lambda t: t[0])[:4]]
