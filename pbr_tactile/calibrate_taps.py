"""Calibration from taps: contacts tie the membrane's turn and constrain the shading.

One no-contact image sees each LED's whole turn (the membrane's rotation plus the LED's
azimuth) but not the membrane's own: the membrane is rotationally symmetric. A tap is
pressed at a known place on the membrane, so where its contact appears in the real image
gives the membrane's rotation, and with it each LED's azimuth.

Each tap t is rendered per source like the no-contact basis, at a grid point of the
calibration (its few best by the no-contact fit, ``calibrate.TAP_GRID_POINTS``, each
fitted with the taps and the best joint fit kept: one image ranks absorption and
scattering poorly) and with the same seed (common random numbers): its change from the
no-contact basis C_t = B_t - A (h, w, S) is the contact's, with little noise. Where an
LED sits matters for the contact's shading (turning all LEDs by 0.15 rad changed a
cylinder tap's change by 36-48 % of its RMS), so each tap is rendered with every LED at
azimuths -AZIMUTH_STEP_RAD, 0 and +AZIMUTH_STEP_RAD (with the no-contact basis of the
same turn), and source s's change is the quadratic through them in its LED's azimuth
phi_m(s). The tap's image is modelled as (``ImageModel.tap_design``)

    I_t(p) = clip((V(p) sum_s g_sc [A_s(T_m(s)^-1 p) + C_ts(phi_m(s); T^-1 p)] + o_c) ** (1 / gamma), 0, sat_c)

the change moving with the membrane (T: rotation theta, no LED azimuth: the azimuth is
in the render), the rest as the no-contact image. With LED groups a tap is rendered with
every LED where it sits, each group spread over the span the no-contact image fitted, and
its change summed per group (``tap_spec``): the dent breaks the symmetry that lets the
no-contact basis render one LED per group. The LEDs' azimuths are fitted as one
turn of the LED ring against the membrane (``calibrate.NOT_IDENTIFIABLE_WITH_TAPS``): that
turn shades every contact, while each LED's own azimuth about the ring was not recovered
from the reference's images.

Taps alternate (``scenes.captures``): even ones are fitted with the no-contact image's
training sectors, odd ones judge. A tap is fitted and judged on its contact region
(``scenes.captures.RealTaps.regions``): its annotated disc, or else found in the real
images themselves.

The fit starts from the no-contact fit. That fit pins each LED's whole turn only loosely
(each LED lights the membrane nearly all round, and its gains are free: on a virtual
sensor a whole turn 0.47 rad off cost 0.5 % of the loss), so the starts keep its tied
values (the azimuths' spread, the camera, the leaks) and scan the membrane's rotation
round the whole circle in SCAN_STEP_RAD steps; the best few are refined by the same
bounded least squares. With a known alignment (``ImageModel.known_alignment``) there is
nothing to scan: the fit starts from the no-contact fit itself.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from scenes import captures
from scenes.camera import Camera
from scenes.captures import RealTaps
from scenes.images import block_mean
from scenes.spec_read import with_led_groups

from .basis import basis_layout, emitter_basis, led_of_source
from .effects import Effects
from .image_fit import ImageFit, ImageFitter, TapView, debiased
from .image_model import ImageModel, Nonlinear
from .real_image import film_factor

#: Each tap is rendered with every LED at azimuths -this, 0 and +this (radians) for its
#: change's quadratic in the azimuth.
AZIMUTH_STEP_RAD = 0.15
#: The membrane's rotation is scanned in steps of this about each start.
SCAN_STEP_RAD = math.radians(2.0)


def tap_spec(spec, spans: tuple = ()) -> tuple:
    """How a tap of ``spec`` is rendered: (the spec, photons per LED as a share of the
    basis', each LED's unit). A contact breaks the membrane's symmetry, so a group's LEDs
    cannot be one render turned along the arc as in the no-contact basis
    (``basis.basis_layout``): the tap is rendered with every LED where it sits, each group
    spread over ``spans`` (rad, per unit: the no-contact fit's, where the joint fit starts;
    () the spec's), and each LED's photons are the basis' times units / LEDs, so that a
    unit's change has about the noise of the basis' own source."""
    rendered, _, _, unit, _ = basis_layout(spec)
    if not spec.led_groups:
        return spec, 1.0, unit
    if spans:
        first = len(rendered.leds) - len(spec.led_groups)
        spec = with_led_groups(spec, [dataclasses.replace(g, arc_span_rad=float(spans[first + i]))
                                     for i, g in enumerate(spec.led_groups)])
    return spec, len(rendered.leds) / len(spec.leds), unit


def per_unit(basis: dict, unit: np.ndarray, names, key: str = "mean") -> np.ndarray:
    """(h, w, U) a per-LED render's sources (``led<m>``, ``led<m>_leak``) summed into the
    units whose sources are ``names``: LED m's into unit ``unit[m]``'s of the same kind.
    ``key``: the render's "mean", or its "variance" (summed as if the sources' noise were
    independent)."""
    index = {str(n): k for k, n in enumerate(names)}
    out = np.zeros((*basis[key].shape[:2], len(names)))
    for k, (name, m) in enumerate(zip(basis["names"], led_of_source(basis["names"]))):
        target = f"led{unit[m]}" + ("_leak" if str(name).endswith("_leak") else "")
        if target not in index:
            raise ValueError(f"tap_changes: the tap's source {name} has no unit among the basis' "
                             f"{[str(n) for n in names]}")
        out[..., index[target]] += basis[key][..., k]
    return out


def tap_changes(spec, mesh, camera, effects, film, taps: RealTaps, no_contact: dict, photons: int, spp: int,
                passes: int, seed: int, use_cache: bool = True, progress=None, azimuths: bool = True,
                known: dict | None = None, spans: tuple = ()) -> dict:
    """Each tap's per-source change from the no-contact basis, as a function of the LEDs'
    azimuths (module doc): ``change``, ``slope``, ``curve`` (T, h, w, S). ``no_contact``:
    ``emitter_basis`` of the same spec, effects, film and seed. ``azimuths`` False: the
    change with the LEDs where the spec has them only (``slope`` and ``curve`` None).
    ``known``: changes already rendered with the LEDs there, by tap index (each (h, w, S)).
    With LED groups each tap and its no-contact counterpart are rendered per LED
    (``tap_spec``, groups spread over ``spans``) and summed into the basis' units."""
    from scenes.profile import turn_leds

    spec, share, unit = tap_spec(spec, spans)
    grouped = bool(spec.led_groups)
    photons = max(1, int(round(photons * share)))
    leds, known = len(spec.leds), known or {}
    turns = (-AZIMUTH_STEP_RAD, 0.0, AZIMUTH_STEP_RAD) if azimuths else (0.0,)
    at = {}
    for a in turns:
        turned = turn_leds(spec, (a,) * leds)
        base = no_contact if a == 0 and not grouped else emitter_basis(turned, mesh, camera, effects, film, photons,
                                                                       spp, passes, seed, use_cache)
        out = []
        for t, depth in enumerate(taps.depths):
            if a == 0 and t in known:
                out.append(known[t])
                continue
            basis = emitter_basis(turned, mesh, camera, effects, film, photons, spp, passes, seed, use_cache,
                                  depth=depth, ref_depth=taps.ref_depth)
            if list(basis["names"]) != list(base["names"]):
                raise ValueError("tap_changes: the tap's sources differ from the no-contact basis'")
            change = {"mean": basis["mean"] - base["mean"], "names": basis["names"]}
            out.append(per_unit(change, unit, no_contact["names"]) if grouped else change["mean"])
            if progress is not None:
                progress(len(at) * len(taps.depths) + len(out), len(turns) * len(taps.depths))
        at[a] = np.stack(out)
    if not azimuths:
        return {"change": at[0.0], "slope": None, "curve": None}
    d = AZIMUTH_STEP_RAD
    minus, zero, plus = at[-d], at[0.0], at[d]
    return {"change": zero, "slope": (plus - minus) / (2 * d), "curve": (plus - 2 * zero + minus) / (2 * d * d)}


def starts(fit: ImageFit) -> list[Nonlinear]:
    """Starting points for a fit with taps from a no-contact fit (module doc): its tied
    values, with the membrane's rotation every SCAN_STEP_RAD round the circle."""
    nl = fit.nl.tied()
    steps = int(round(2 * math.pi / SCAN_STEP_RAD))
    return [dataclasses.replace(nl, rotation_rad=2 * math.pi * i / steps) for i in range(steps)]


def fit_with_taps(model: ImageModel, real: np.ndarray, train: np.ndarray, views: list[TapView], start: ImageFit,
                  leak: bool = True, max_evaluations: int = 1500, keep: int = 2, common_turn: bool = True) -> ImageFit:
    """The no-contact image's training pixels and the fitted taps together, refined from
    the ``keep`` best of ``starts(start)`` (module doc). ``common_turn`` False: each LED's
    azimuth free, where the data can tell them apart (not so on the reference's own images:
    see ``calibrate.NOT_IDENTIFIABLE_WITH_TAPS``)."""
    fitter = ImageFitter(model, real, train, leak=leak, taps=views, common_turn=common_turn)
    if model.known_alignment:
        return fitter.fit(start.nl, max_evaluations)
    screened = sorted(starts(start), key=lambda nl: fitter.loss(nl.vector()))[:keep]
    return min((fitter.fit(nl, max_evaluations) for nl in screened), key=lambda f: f.loss)


def tap_scores(model: ImageModel, fit: ImageFit, views: list[TapView], background: np.ndarray) -> dict:
    """Per channel over the given taps' contact regions: the MAE of the tap image, and the
    R^2 of its change from the no-contact image (predicted change against real change)."""
    saturation = (1.0, 1.0, 1.0)
    bg_pred = model.render(fit.nl, fit.gains, fit.offset, saturation)
    pred_change, real_change, err = [], [], []
    for view in views:
        pred = model.render(fit.nl, fit.gains, fit.offset, saturation, change=view.at(fit.nl, model.led))
        pixels = view.pixels & model.inside
        err.append(np.abs(pred - view.real)[pixels])
        pred_change.append((pred - bg_pred)[pixels])
        real_change.append((view.real - background)[pixels])
    out = {"mae": {}, "change_r2": {}, "pixels": int(sum(len(e) for e in err))}
    if not err:
        return out
    err, pc, rc = np.concatenate(err), np.concatenate(pred_change), np.concatenate(real_change)
    for c, ch in enumerate("rgb"):
        out["mae"][ch] = float(err[:, c].mean())
        total = float(np.sum((rc[:, c] - rc[:, c].mean()) ** 2))
        out["change_r2"][ch] = float(1 - np.sum((rc[:, c] - pc[:, c]) ** 2) / total) if total > 0 else float("nan")
    return out


def film_views(taps: RealTaps, changes: dict, background_film: np.ndarray, inside: np.ndarray,
               film: tuple[int, int]) -> list[TapView]:
    """Each tap at the film's size with its change (``tap_changes``) and contact region."""
    views = []
    reals = np.stack([block_mean(np.asarray(image, np.float64), film_factor(image.shape, film))
                      for image in taps.images])
    regions = taps.regions(background_film, inside, reals)
    for t, real in enumerate(reals):
        slope, curve = (None, None) if changes["slope"] is None else (changes["slope"][t], changes["curve"][t])
        views.append(TapView(changes["change"][t], real, regions[t], slope=slope, curve=curve))
    return views


def rank_with_taps(taps, fit: ImageFit, model: ImageModel, basis: dict, r: np.ndarray, train: np.ndarray,
                    effects: Effects, spec, mesh, camera: Camera, film, photons, spp, passes, seed, leak,
                    use_cache) -> dict:
    """A grid point judged by the fitted taps with the LEDs where the spec has them (the
    cheap form of ``_fit_taps``: a sixth of its renders, the same at every point, so the
    losses compare): ``loss``, ``noise`` (``_debiased``), ``converged``, and ``known``
    the changes rendered (by tap index), which the full fit reuses."""
    fitted = np.flatnonzero(captures.split(len(taps.ids)))
    subset = taps.subset(fitted)
    changes = tap_changes(spec, mesh, camera, effects, film, subset, basis, photons, spp, passes, seed, use_cache,
                          azimuths=False, spans=fit.nl.span_rad)
    views = [v for v in film_views(subset, changes, r, model.inside, film) if v.pixels.sum() >= captures.MIN_REGION]
    joint = fit_with_taps(model, r, train, views, fit, leak) if views else None
    if joint is not None:
        joint = debiased(joint, model, basis, [train] + [v.pixels for v in views])
    return {"loss": math.inf if joint is None else joint.loss, "noise": 0.0 if joint is None else joint.noise,
            "converged": joint is not None and joint.converged,
            "known": dict(zip(fitted.tolist(), changes["change"]))}


def fit_taps(taps, fit: ImageFit, model: ImageModel, basis: dict, r: np.ndarray, train: np.ndarray,
              effects: Effects, spec, mesh, camera: Camera, film, photons, spp, passes, seed, leak, use_cache,
              known: dict | None = None):
    """The fit with taps (``pbr_tactile.calibrate_taps``): (fit, fitted taps' views, the
    report's ``taps`` section). ``known``: zero-azimuth changes already rendered."""
    changes = tap_changes(spec, mesh, camera, effects, film, taps, basis, photons, spp, passes, seed, use_cache,
                          known=known, spans=fit.nl.span_rad)
    views = film_views(taps, changes, r, model.inside, film)
    seen = [int(v.pixels.sum()) >= captures.MIN_REGION for v in views]
    fitted = captures.split(len(views))
    fit_views = [v for v, f, ok in zip(views, fitted, seen) if f and ok]
    judge_views = [v for v, f, ok in zip(views, fitted, seen) if not f and ok]
    if not fit_views:
        raise ValueError(f"none of the fitted taps ({', '.join(np.asarray(taps.ids)[fitted])}) shows a contact: each "
                         f"differs from the no-contact image in fewer than {captures.MIN_REGION} film pixels by more than "
                         f"{captures.CHANGE_LEVEL:.3f}")
    background_only = fit
    fit = fit_with_taps(model, r, train, fit_views, background_only, leak)
    ids = np.asarray(taps.ids)
    report = {
        "fitted": ids[fitted & np.array(seen)].tolist(), "judged": ids[~fitted & np.array(seen)].tolist(),
        "without_contact": ids[~np.array(seen)].tolist(),
        "split": "alternate taps: even ones (from the capture's even samples) fitted with the image's training "
                 "sectors, odd ones (from its odd samples) judged; each on its contact region (its annotated disc, "
                 "else where the real tap differs from the real no-contact image)",
        "heldout": tap_scores(model, fit, judge_views, r), "fit": tap_scores(model, fit, fit_views, r),
        "heldout_before_taps": tap_scores(model, background_only, judge_views, r),
    }
    return fit, fit_views, report

