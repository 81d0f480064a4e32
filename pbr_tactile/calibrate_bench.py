"""Blind recovery benchmark of calibration: virtual sensors with hidden parameters.

Each case draws a virtual sensor: the reference's physical effects from the calibration
grid's values (the basis is rendered on that grid, so recovery measures the search, not
interpolation between grid points), and the camera, lens, alignment and LED parameters
from the stated ranges below (each LED group's centre and span, each single LED's
azimuth, the lens' k1). Its no-contact image is rendered with every LED where it truly
is (``virtual_build``: a group's LEDs along its drawn arc, summed into the group's unit)
and then moved by its rotation, scale, shift and lens, with another seed than the
calibration's basis (so its Monte Carlo noise is its own), as wide as the calibration's
basis sees (``basis.basis_camera``), and calibrated from without its values.

Scoring, per identifiable parameter:
- positive quantities (gamma, the lens' illumination at the circle's edge V(1),
  each unit's leak fraction where it is at least LEAK_MIN, each unit's gains relative to
  the brightest gain, each group's arc span, the grid's effects): |fit - true| / true;
- zero-centred ones (rotation, shift): |fit - true| / the half-width of their range;
- the lens, whose scale and k1 one image does not tell apart, by where it puts the rays
  (``lens_error_px``) over the half-width of the shift's range; the scale (relatively)
  and k1 (as the share by which it moves the image circle's edge, over its range's
  half-width) are reported apart and not scored (``reported_not_scored``).
With gains free per LED, LEDs whose images differ only by a turn can swap: the rotation
is known modulo 2 pi / L and the LEDs' parameters up to that renaming, so scoring first
finds the renaming (the one that best matches the rotation).

``heldout_mae_over_noise``: the MAE on the held-out sectors over the virtual image's own
Monte Carlo noise (its standard error, carried through the camera's response), stated
per case (``noise``). ``mc_error``: what that noise and the basis' own make of each
scored nonlinear parameter, to first order (``ImageFitter.covariance``), in its score's
units; a case's parameters whose Monte Carlo error exceeds the TOLERANCE are listed in
``beyond_tolerance``: at its photons, that case cannot score them within it. It takes
the pixels' noise as independent, and the photon map's is not: the same virtual sensor
rendered with four seeds and fitted from its truth scattered 5 times wider in the
response exponent than this predicts, and every fit missed the truth by the same 14 %
(the calibration's basis is one noisy render shared by all fits), so it is a lower
bound.

With taps (``taps`` > 0): the same taps of the base protocol (the sphere, spread evenly
over it; depth maps from the MuJoCo rig) are rendered for each virtual sensor like its
no-contact image, with the same seed (one sensor's captures share its scene's noise;
the change between a tap and the no-contact image is then nearly noise-free, as a real
camera's 8-bit noise is small at the film's resolution). Calibration fits
alternate taps and holds out the others (``pbr_tactile.calibrate_taps``). The rotation
is then scored as the membrane's own, and the LEDs' mean azimuth as their common turn
(zero-centred; calibration ties them to it, ``calibrate.NOT_IDENTIFIABLE_WITH_TAPS``);
``heldout_taps`` reports the held-out taps' MAE over their contact regions against the
virtual taps' own noise (``tap_mae_over_noise``) and the R^2 of their contact changes.
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from scenes.camera import Camera, project
from scenes.profile import turn_leds
from scenes.spec_read import with_led_groups

from .basis import BASIS_EFFECTS, basis_camera, basis_layout, emitter_basis
from .calibrate import GRID, calibrate_background
from .calibrate_taps import per_unit, tap_spec
from .effects import Effects
from .image_model import ImageModel, Nonlinear
from .scene import led_sources

#: Ranges the hidden values are drawn from (uniform).
RANGES = {
    "rotation_rad": (-math.pi / 3, math.pi / 3),
    "led_azimuth_rad": (-0.15, 0.15),
    "leak": (0.0, 0.6),
    "scale": (0.9, 1.1),
    "shift_px": (-15.0, 15.0),
    "edge_illumination": (0.35, 1.0),
    "gamma": (1.6, 2.6),
    "gain": (0.2, 1.0),
    # the real lens' k1 against the spec's, as the share by which it moves the image
    # circle's edge (k1 e^2, e the edge's radius in focal lengths); no unit-to-unit spread
    # of the lens is published (estimate: as wide as the scale's)
    "lens_edge_shift": (-0.1, 0.1),
    # each LED group's arc span as a share of the spec's (estimate: the crown's slots are
    # hand-fitted, 3 to 6 LEDs per colour)
    "span_share": (0.8, 1.2),
}
#: The recovery tolerance: a scored error within it counts in ``share_within_10pct``; a
#: parameter whose Monte Carlo error exceeds it cannot be recovered at the case's photons.
TOLERANCE = 0.10
#: Leak fractions below this are scored as absent, not relatively.
LEAK_MIN = 0.1
#: The virtual image's seed differs from the basis' by this.
SEED_OFFSET = 1000


def draw(rng: np.random.Generator, units: int, grid: dict, spans: tuple = (), edge: float = 1.0,
         k1: float = 0.0) -> tuple[Nonlinear, np.ndarray, dict]:
    """Hidden nonlinear parameters, gains (U, 3) and grid effects of one virtual sensor of
    ``units`` units (``basis.basis_layout``): each group's span drawn about ``spans`` (the
    spec's, 0 for a single LED; () without groups), the lens' k1 about the spec's ``k1``
    from its shift of the image circle's edge, ``edge`` focal lengths out."""
    u = lambda name, n=None: rng.uniform(*RANGES[name], n)  # noqa: E731
    edge_light = u("edge_illumination")
    nl = Nonlinear(float(u("rotation_rad")), tuple(u("led_azimuth_rad", units)), tuple(u("leak", units)),
                   float(u("scale")), tuple(u("shift_px", 2)), (float(edge_light - 1.0), 0.0), float(u("gamma")))
    gains = u("gain", (units, 3))
    effects = {name: float(rng.choice(values)) for name, values in grid.items()}
    share = u("span_share", len(spans))
    nl = dataclasses.replace(nl, span_rad=tuple(float(s * f) for s, f in zip(spans, share)),
                             k1=float(k1 + u("lens_edge_shift") / edge**2))
    return nl, gains, effects


def virtual_build(spec, nl: Nonlinear) -> tuple:
    """The virtual sensor's LEDs where they truly are, and how they are rendered: each
    single LED turned by its unit's azimuth, each group's centre turned by its unit's and
    its LEDs spread over its unit's span; (that spec, photons per LED as a share of the
    basis', each LED's unit: ``calibrate_taps.tap_spec``)."""
    _, _, spans, unit, _ = basis_layout(spec)
    first = len(spans) - len(spec.led_groups)
    if spec.led_groups:
        spec = with_led_groups(spec, [
            dataclasses.replace(g, arc_centre_rad=g.arc_centre_rad + nl.led_azimuth_rad[first + i],
                                arc_span_rad=nl.span_rad[first + i]) for i, g in enumerate(spec.led_groups)])
        unit = basis_layout(spec)[3]
    spec = turn_leds(spec, [nl.led_azimuth_rad[m] if led.group is None else 0.0 for led, m in zip(spec.leds, unit)])
    return tap_spec(spec)


def virtual_render(build: tuple, names, mesh, camera, effects: Effects, film, photons: int, spp: int, seed: int,
                   use_cache: bool, depth=None, ref_depth=None) -> tuple[np.ndarray, np.ndarray]:
    """(mean, variance) (h, w, S) of a virtual sensor (``virtual_build``) per unit source
    ``names`` (a group's LEDs summed into its unit), without contact or with ``depth``."""
    spec, share, unit = build
    basis = emitter_basis(spec, mesh, camera, effects, film, max(1, int(round(photons * share))), spp, 2, seed,
                          use_cache, depth=depth, ref_depth=ref_depth)
    if not spec.led_groups:
        return basis["mean"], basis["variance"]
    return per_unit(basis, unit, names), per_unit(basis, unit, names, "variance")


def lens_error_px(camera: Camera, nl: Nonlinear, scale: float, k1: float, step: int = 8) -> float:
    """RMS over the image circle (every ``step``-th camera pixel) of how far a lens of
    ``scale`` and ``k1`` puts each ray from where the lens of ``nl`` does, camera pixels,
    both at ``nl``'s principal point: how well the lens' mapping is known."""
    true = nl.alignment(0.0, camera.k2).lens(camera)
    fitted = dataclasses.replace(nl, scale=scale, k1=k1).alignment(0.0, camera.k2).lens(camera)
    v, u = np.mgrid[0:camera.height:step, 0:camera.width:step].astype(np.float64)
    mx = camera.cx if camera.mask_cx is None else camera.mask_cx
    my = camera.cy if camera.mask_cy is None else camera.mask_cy
    inside = np.hypot(u - mx, v - my) <= camera.mask_radius_px
    x, y = true.slopes(u[inside], v[inside])
    uv = project(np.stack([x, y, np.ones_like(x)], axis=-1), fitted)
    d2 = (uv[..., 0] - u[inside]) ** 2 + (uv[..., 1] - v[inside]) ** 2
    return float(np.sqrt(np.nanmean(d2)))


def _errors(fit: dict, nl: Nonlinear, gains: np.ndarray, effects: dict, leds: int, camera: Camera,
            taps: bool = False) -> tuple[dict[str, float], dict[str, float]]:
    """(scored, reported) relative errors (module doc): those of what the data identify,
    and those of the parts of a combination, reported and not scored; ``leds``: the fit's
    units."""
    turn = 2 * math.pi / leds
    # without taps the fit reports the tied rotation, with taps the membrane's own
    d = fit["rotation_rad"] - (nl.rotation_rad if taps else nl.tied().rotation_rad)
    k = min(range(leds), key=lambda shift: abs(math.remainder(d - shift * turn, 2 * math.pi)))
    rot_err = abs(math.remainder(d - k * turn, 2 * math.pi))
    perm = [(j + k) % leds for j in range(leds)]  # fitted LED j sits where true LED j + k does
    half = lambda name: (RANGES[name][1] - RANGES[name][0]) / 2  # noqa: E731
    edge = camera.mask_radius_px / camera.f
    out = {"rotation_rad": rot_err / half("rotation_rad"),
           "gamma": abs(fit["gamma"] - nl.gamma) / nl.gamma,
           "shift_px": float(np.max(np.abs(np.subtract(fit["shift_px"], nl.shift_px)))) / half("shift_px"),
           "edge_illumination": abs(sum(fit["vignetting"]) - sum(nl.vignetting)) / (1 + sum(nl.vignetting)),
           "lens_mapping_px": lens_error_px(camera, nl, fit["scale"], fit["k1"]) / half("shift_px")}
    reported = {"scale": abs(fit["scale"] - nl.scale) / nl.scale,
                "lens_edge_shift": abs(fit["k1"] - nl.k1) * edge**2 / half("lens_edge_shift")}
    fitted_gains = np.asarray(fit["led_gains"])
    rel_fit = fitted_gains / fitted_gains.max()
    rel_true = gains / gains.max()
    for j, true in enumerate(perm):
        leak_true, leak_fit = nl.leak[true], fit["led_leak"][j]
        out[f"led{true}_leak"] = abs(leak_fit - leak_true) / max(leak_true, LEAK_MIN)
        for c, ch in enumerate("rgb"):
            out[f"led{true}_gain_{ch}"] = abs(rel_fit[j, c] - rel_true[true, c]) / rel_true[true, c]
        if nl.span_rad and nl.span_rad[true] > 0:
            out[f"led{true}_span"] = abs(fit["arc_span_rad"][j] - nl.span_rad[true]) / nl.span_rad[true]
    if taps:
        # the LEDs' common turn against the membrane (each LED's own is not identifiable)
        out["led_turn"] = abs(np.mean(fit["led_azimuth_rad"]) - np.mean(nl.led_azimuth_rad)) / half("led_azimuth_rad")
    for name, value in effects.items():
        out[name] = abs(fit["effects"][name] - value) / value if value else abs(fit["effects"][name])
    return out, reported


def mc_errors(standard_errors: dict | None, nl: Nonlinear, leds: int) -> dict[str, float]:
    """The Monte Carlo error of each scored nonlinear parameter a case's calibration
    reports (``standard_errors``: the fit's, from the virtual image's and the basis'
    noise; None with taps), in the units it is scored in (``_errors``); the gains (solved
    inside the fit) and the lens' mapping are not covered."""
    if not standard_errors:
        return {}
    half = lambda name: (RANGES[name][1] - RANGES[name][0]) / 2  # noqa: E731
    se = standard_errors
    out = {"rotation_rad": se["rotation_rad"] / half("rotation_rad"), "gamma": se["gamma"] / nl.gamma,
           "shift_px": max(se.get("shift_u", 0.0), se.get("shift_v", 0.0)) / half("shift_px"),
           "edge_illumination": se.get("edge_illumination", 0.0) / (1 + sum(nl.vignetting))}
    for m in range(leds):
        if f"leak[{m}]" in se:
            out[f"led{m}_leak"] = se[f"leak[{m}]"] / max(nl.leak[m], LEAK_MIN)
        if nl.span_rad and nl.span_rad[m] > 0 and f"span_rad[{m}]" in se:
            out[f"led{m}_span"] = se[f"span_rad[{m}]"] / nl.span_rad[m]
    return out


def protocol_taps(spec, mesh, count: int) -> tuple[list, np.ndarray, np.ndarray]:
    """``count`` taps of the base protocol (the sphere) at distinct places, spread evenly over it, with their
    depth maps from the MuJoCo rig: (taps, depths (T, H, W), the no-contact depth map)."""
    from scenes.protocol import base_protocol
    from scenes.rig import tap_depths

    protocol = base_protocol(spec, mesh, ["sphere"])
    # each place once (every path starts at the tip)
    places = {}
    for tap in protocol.taps:
        places.setdefault(tuple(np.round(tap.point, 4)), tap)
    distinct = list(places.values())
    pick = np.unique(np.linspace(0, len(distinct) - 1, count).round().astype(int))
    taps = [distinct[i] for i in pick]
    replay = tap_depths(spec, taps, mesh)
    try:
        ref_depth = next(replay)[0]
        depths = [d for d, _ in replay]
    finally:
        replay.close()
    return taps, np.stack(depths).astype(np.float32), np.asarray(ref_depth, np.float32)


def virtual_taps(build: tuple, names, mesh, camera, effects: Effects, still: Nonlinear, gains: np.ndarray, depths,
                 ref_depth, film, photons: int, spp: int, seed: int, use_cache: bool, ids) -> tuple:
    """A virtual sensor's taps at the camera's size: (RealTaps, their noise level).
    ``build``: the sensor's LEDs where they are (``virtual_build``), per unit source
    ``names``; ``still``: its parameters with zero azimuths and no arcs (the LEDs' places
    are in the render), whose alignment then moves the image. The noise level is the mean
    Monte Carlo standard error of the taps' images inside the image circle, carried
    through the response."""
    from scenes.captures import RealTaps

    k = camera.height // film[1]
    images, noise = [], []
    for depth in depths:
        mean, variance = virtual_render(build, names, mesh, camera, effects, film, photons, spp, seed, use_cache,
                                        depth=depth, ref_depth=ref_depth)
        model = ImageModel(mean, names, camera, (camera.cx, camera.cy, camera.mask_radius_px))
        image = model.render(still, gains, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
        images.append(np.repeat(np.repeat(image, k, axis=0), k, axis=1))
        noise.append(_noise(model, model.prediction_variance(variance, still, gains)))
    return RealTaps(np.stack(images), depths, ref_depth, list(ids)), float(np.mean(noise))


def _noise(model: ImageModel, image_variance: np.ndarray) -> float:
    """Mean Monte Carlo standard error inside the circle of a virtual image whose
    variance through the camera's response is ``image_variance`` (h, w, 3)."""
    return float(np.mean(np.sqrt(image_variance)[model.inside]))


def benchmark(spec, mesh, camera, cases: int = 6, seed: int = 0, film: tuple[int, int] = (160, 120),
              grid: dict | None = None, photons: int = 1 << 18, spp: int = 32, progress=None, cold: bool = False,
              taps: int = 0, on_case=None, fast_path_fit=None) -> dict:
    """Run ``cases`` blind recoveries; returns the benchmark's JSON (see the module doc).
    cold : render every basis afresh (no disk cache), as a first calibration would.
    taps : virtual taps per sensor (at most calibrate_taps.MAX_TAPS; 0: the no-contact
    image only).
    on_case : called after each case with the summary of the cases so far (a run that is
    stopped keeps what it finished).
    fast_path_fit : with taps, the fast path's LED fit (``calibrate_background``)."""
    from scenes.captures import MAX_TAPS

    if not 0 <= taps <= MAX_TAPS:
        raise ValueError(f"taps must be in [0, {MAX_TAPS}], got {taps}")
    grid = GRID if grid is None else grid
    rng = np.random.default_rng(seed)
    per_case: list[dict] = []
    rendered, _, spans, _, _ = basis_layout(spec)
    units = len(rendered.leds)
    names = [src["name"] for src in led_sources(rendered, Effects().with_settings(
        [f"{k}={v}" for k, v in BASIS_EFFECTS.items()]))]
    if taps:
        protocol, depths, ref_depth = protocol_taps(spec, mesh, taps)
        ids = [f"{t.object}_{i}" for i, t in enumerate(protocol)]
    for case in range(cases):
        nl, gains, effects = draw(rng, units, grid, spans, camera.mask_radius_px / camera.f, camera.k1)
        fx = Effects().with_settings([f"{k}={v}" for k, v in {**BASIS_EFFECTS, **effects}.items()])
        # the virtual sensor's own render: its LEDs where they truly are, at the film's size,
        # with its own seed (its own noise; its taps share it, as one sensor's captures
        # share the scene); seen as wide as the calibration's basis, so that its lens may
        # see wider than the spec's (with taps the spec's camera, as the calibration's)
        build = virtual_build(spec, nl)
        still = dataclasses.replace(nl, led_azimuth_rad=(0.0,) * units, span_rad=())
        case_seed = seed + SEED_OFFSET + case
        seen = camera if taps else basis_camera(camera)
        mean, variance = virtual_render(build, names, mesh, seen, fx, film, photons, spp, case_seed, not cold)
        circle = (camera.cx, camera.cy, camera.mask_radius_px)
        model = ImageModel(mean, names, camera, circle, rendered=seen)
        design = model.design(still)
        gains_scaled = gains / np.percentile(design[model.inside].sum(axis=1), 95)
        image = model.render(still, gains_scaled, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
        k = camera.height // film[1]
        real = np.repeat(np.repeat(image, k, axis=0), k, axis=1)
        real_taps, tap_noise = (None, None) if not taps else virtual_taps(
            build, names, mesh, camera, fx, still, gains_scaled, depths, ref_depth, film, photons, spp, case_seed,
            not cold, ids)
        image_variance = model.prediction_variance(variance, still, gains_scaled)
        t0 = time.perf_counter()
        cal = calibrate_background(real, spec, mesh, camera, film=film, grid=grid, photons=photons, spp=spp, seed=seed,
                                   bootstrap=0, use_cache=not cold, taps=real_taps, fast_path_fit=fast_path_fit,
                                   image_variance=image_variance)
        seconds = time.perf_counter() - t0
        fit = {**cal.report["parameters"], "effects": cal.report["best_effects"]}
        noise = _noise(model, image_variance)
        mae = float(np.mean([cal.report["heldout_mae"][ch] for ch in "rgb" if not cal.report["saturated"][ch]]))
        scored, reported = _errors(fit, nl, gains_scaled, effects, units, camera, taps=bool(taps))
        mc = mc_errors(cal.report["standard_errors"], nl, units)
        record = {"errors": scored, "reported": reported, "noise": noise, "mc_error": mc,
                  "beyond_tolerance": sorted(name for name, e in mc.items() if e > TOLERANCE),
                  "mae_over_noise": mae / noise if noise > 0 else float("nan"),
                  "heldout_r2": cal.report["heldout_r2"], "seconds": seconds,
                  "hidden": {**dataclasses.asdict(nl), "gains": gains_scaled.tolist(), "effects": effects},
                  "fit": fit}
        if taps:
            held = cal.report["taps"]["heldout"]
            before = cal.report["taps"]["heldout_before_taps"]
            record["taps"] = {"tap_mae_over_noise": float(np.mean(list(held["mae"].values()))) / tap_noise,
                              "change_r2": held["change_r2"], "change_r2_before_taps": before["change_r2"],
                              "pixels": held["pixels"], "grid": cal.report["taps"]["grid"]}
        record["grid"] = cal.report["grid"]
        per_case.append(record)
        if on_case is not None:
            on_case(_summary(per_case, seed, taps, grid))
        if progress is not None:
            progress(case + 1, cases)
    return _summary(per_case, seed, taps, grid)


def _summary(per_case: list[dict], seed: int, taps: int, grid: dict) -> dict:
    """The benchmark's JSON over the cases run so far (module doc)."""
    per_parameter: dict[str, list[float]] = {}
    for record in per_case:
        for name, err in record["errors"].items():
            per_parameter.setdefault(name, []).append(float(err))
    errors = np.concatenate([np.asarray(v) for v in per_parameter.values()])
    reported: dict[str, list[float]] = {}
    for record in per_case:
        for name, err in record.get("reported", {}).items():
            reported.setdefault(name, []).append(float(err))
    tap_scores = [r["taps"] for r in per_case if "taps" in r]
    return {
        "cases": len(per_case),
        "seed": seed,
        "median_relative_error": float(np.median(errors)),
        "share_within_10pct": float(np.mean(errors <= TOLERANCE)),
        "per_parameter": {name: {"median": float(np.median(v)), "max": float(np.max(v))}
                          for name, v in per_parameter.items()},
        "reported_not_scored": {name: {"median": float(np.median(v)), "max": float(np.max(v))}
                                for name, v in reported.items()},
        "heldout_mae_over_noise": float(np.median([r["mae_over_noise"] for r in per_case])),
        "noise": [r["noise"] for r in per_case],
        "mc_error": {name: float(np.median([r["mc_error"][name] for r in per_case if name in r.get("mc_error", {})]))
                     for name in sorted({n for r in per_case for n in r.get("mc_error", {})})},
        "beyond_tolerance": {i: r["beyond_tolerance"] for i, r in enumerate(per_case) if r.get("beyond_tolerance")},
        "heldout_r2": [r["heldout_r2"] for r in per_case],
        "taps": taps,
        "heldout_taps": tap_scores,
        "tap_mae_over_noise": float(np.median([t["tap_mae_over_noise"] for t in tap_scores])) if taps else None,
        "seconds_per_case": float(np.median([r["seconds"] for r in per_case])),
        "per_case": per_case,
        "scoring": __doc__.split("\n\n", 3)[2],
        "ranges": {k: list(v) for k, v in RANGES.items()},
        "grid": {k: list(v) for k, v in grid.items()},
    }
