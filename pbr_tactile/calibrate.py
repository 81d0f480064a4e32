"""Calibrate the physically based reference to a real sensor unit from its no-contact
image, and its taps if given.

The reference renders one grey basis image per source (``pbr_tactile.basis``) at each
point of a coarse grid of physical effects; the image model (``pbr_tactile.image_model``)
is fitted at each, on alternate angular sectors of the image circle, and the best point
is kept. The odd sectors judge: held-out R^2 per unsaturated channel, with bootstrap
intervals (``pbr_tactile.real_image``). With taps, the few best points are fitted with
them too (``pbr_tactile.calibrate_taps``). The fast path's background term is fitted
alongside (``pbr_tactile.fast_background``), and its LED constants by the caller's
``fast_path_fit``.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from scenes.camera import Camera, lens_angle
from scenes.captures import MAX_TAPS, split
from scenes.image_stats import percentile_interval, r2
from scenes.images import block_mean
from scenes.profile import Alignment, CameraProfile, Profile
from scenes.spec import SensorSpec

from . import calibrate_taps as ct
from .basis import BASIS_EFFECTS, basis_camera, basis_layout, emitter_basis, grid_bases
from .effects import Effects
from .fast_background import fit_fast_background
from .image_fit import ImageFit, ImageFitter, TapView, debiased, tied_errors
from .image_model import GAMMA_BOUNDS, WEBCAM_BLACK, WEBCAM_GAMMA, ImageModel
from .real_image import (
    CIRCLE_THRESHOLD,
    CLIP_LEVEL,
    SATURATED_SHARE,
    SECTORS,
    check_real,
    film_factor,
    film_sectors,
    heldout_interval,
    image_circle,
    sector_index,
)

#: The default grid of physical effects searched (common random numbers across it).
GRID = {"absorption_per_m": (5.0, 20.0, 80.0), "scattering_per_m": (10.0, 50.0, 250.0)}
#: With taps, the taps are rendered and fitted at this many of the grid's best points by
#: the no-contact fit, and the best joint fit is kept: one no-contact image ranks the
#: grid's absorption and scattering poorly (a blind benchmark's sensor at 80 and 250 per
#: m was fitted at 5 and 10), while a contact's shading depends on them.
TAP_GRID_POINTS = 3
#: Bootstrap resamples of the training sectors.
BOOTSTRAP = 16


@dataclass
class Calibration:
    """What ``calibrate_background`` found: the profile, the report (JSON-able) and the
    film-sized images behind it (real, before, after)."""

    profile: Profile
    report: dict
    images: dict


def _grid_points(grid: dict) -> list[dict]:
    names = list(grid)
    points = [{}]
    for name in names:
        points = [{**p, name: float(v)} for p in points for v in grid[name]]
    return points


def calibrate_background(real: np.ndarray, spec: SensorSpec, mesh, camera: Camera, film: tuple[int, int] = (160, 120),
                         grid: dict | None = None, photons: int = 1 << 18, spp: int = 32, passes: int = 2,
                         seed: int = 0, bootstrap: int = BOOTSTRAP, leak: bool = True, use_cache: bool = True,
                         progress=None, taps=None, fast_path_fit=None, image_variance=None,
                         fast_taps=None, camera_known: bool = False, spectral_gains: bool = False,
                         webcam: bool = False) -> Calibration:
    """Calibrate the reference to one real no-contact image (H, W, 3) in [0, 1], and to
    its sensor's taps if given.

    Fits on the even angular sectors of the image circle and judges on the odd ones (see
    the module doc); ``grid`` maps Effects names to the values searched (default GRID);
    ``leak`` False fits with no light into the glass core. ``taps``
    (``pbr_tactile.calibrate_taps.RealTaps``): rendered at the TAP_GRID_POINTS best grid
    points of the no-contact fit and fitted together with the image there, the best joint
    fit kept, alternate taps held out (see that module). ``fast_path_fit``: with taps, a
    callable (spec, mesh, camera, profile, taps, real) -> (the profile's ``phong`` table,
    the report's ``fast_path.taps`` section) that fits the fast path's LED constants to
    them (the phong renderer plugin's ``calibrate``: this package imports no other
    renderer); None leaves them out. ``fast_taps``: the taps it fits instead of ``taps``
    (more than the reference can render: its fit costs no render of the reference).
    ``spectral_gains``: each LED's light reaches the channels through its spectrum under
    the camera's filters, one power per LED and one white balance per channel
    (``pbr_tactile.image_model``), instead of a free gain per LED and channel.
    ``webcam``: the camera's response exponent and black level held to a webcam's
    (``image_model.WEBCAM_GAMMA``, ``WEBCAM_BLACK``).
    ``image_variance``: (h, w, 3) the real image's noise
    variance at the film (without taps, the report's ``standard_errors`` then count it with
    the basis' own Monte Carlo noise; None: the basis' alone). Raises ValueError for a bad
    image; a fit that did not converge is reported (``report["converged"]`` False).
    """
    grid = GRID if grid is None else grid
    for name in grid:
        if name not in Effects.__dataclass_fields__:
            raise ValueError(f"grid: {name!r} is not an effect of the reference ({', '.join(Effects.__dataclass_fields__)})")
    real = check_real(real, camera, "the real no-contact image")
    if taps is not None and len(taps.ids) > MAX_TAPS:
        raise ValueError(f"taps: the reference renders at most {MAX_TAPS} taps of a unit (each per source, at several "
                         f"grid points), got {len(taps.ids)}; fit the fast path on more with fast_taps")
    circle = image_circle(real)
    width, height = film
    factor = film_factor(real.shape, film)
    r = block_mean(real, factor)
    clipped_full = real >= CLIP_LEVEL
    inside_full = real.max(axis=2) > CIRCLE_THRESHOLD
    share = [float(clipped_full[..., c][inside_full].mean()) for c in range(3)]
    saturated = {ch: share[c] > SATURATED_SHARE for c, ch in enumerate("rgb")}
    clipped = block_mean(clipped_full.astype(np.float64), factor) > 0.5
    sector = film_sectors(camera, circle, film)
    rendered, arcs, spans, unit, share_of_span = basis_layout(spec)
    # without taps the basis sees wider than the spec's camera, so the fitted lens may;
    # a tap's change is rendered with the spec's camera, and so is its basis
    wide = basis_camera(camera) if taps is None else camera
    points = _grid_points(grid)
    base = Effects().with_settings([f"{k}={v}" for k, v in BASIS_EFFECTS.items()])
    default = {name: getattr(Effects(), name) for name in grid}
    every = points + ([] if default in points else [default])  # the uncalibrated image's too
    bases, reweighting = grid_bases(every, base, lambda effects, perturb=None: emitter_basis(
        rendered, mesh, wide, effects, film, photons, spp, passes, seed, use_cache, perturb=perturb))
    fits = []
    for i, (point, basis) in enumerate(zip(points, bases)):
        model = ImageModel(basis["mean"], basis["names"], camera, circle, arcs, spans, rendered=wide,
                           lens=not camera_known, known_alignment=camera_known,
                           response=basis["response"] if spectral_gains else None, webcam=webcam)
        train, test = (sector % 2 == 0) & model.inside, (sector % 2 == 1) & model.inside
        fit = ImageFitter(model, r, train, leak=leak).search()
        fits.append((debiased(fit, model, basis, [train]), point, basis, model))
        if progress is not None:
            progress(i + 1, len(points) + 1)
    fit, point, basis, model = min(fits, key=lambda f: f[0].loss - f[0].noise)
    train, test = (sector % 2 == 0) & model.inside, (sector % 2 == 1) & model.inside
    tap_report, fitted_views = None, []
    if taps is not None:
        candidates, ranking, known = sorted(fits, key=lambda f: f[0].loss - f[0].noise)[:TAP_GRID_POINTS], [], None
        if len(candidates) > 1:
            ranking = [{"effects": p, **ct.rank_with_taps(taps, f, m, b, r, train, dataclasses.replace(base, **p), spec,
                                                        mesh, camera, film, photons, spp, passes, seed, leak,
                                                        use_cache)} for f, p, b, m in candidates]
            best = int(np.argmin([rank["loss"] - rank["noise"] for rank in ranking]))
            fit, point, basis, model = candidates[best]
            known = ranking[best].pop("known")
        fit, fitted_views, tap_report = ct.fit_taps(taps, fit, model, basis, r, train, dataclasses.replace(base, **point),
                                                  spec, mesh, camera, film, photons, spp, passes, seed, leak, use_cache,
                                                  known)
        tap_report["grid"] = [{k: v for k, v in rank.items() if k != "known"} for rank in ranking]
    after = model.render(fit.nl, fit.gains, fit.offset, (1.0, 1.0, 1.0))
    default_basis = bases[every.index(default)]
    before = _uncalibrated(rendered, ImageModel(default_basis["mean"], default_basis["names"], camera, circle, arcs,
                                                spans, rendered=wide), r, train)
    judged = {ch: test & ~clipped[..., c] for c, ch in enumerate("rgb")}
    heldout = {ch: r2(after[..., c], r[..., c], judged[ch]) for c, ch in enumerate("rgb")}
    heldout_before = {ch: r2(before[..., c], r[..., c], judged[ch]) for c, ch in enumerate("rgb")}
    mae = {ch: float(np.abs(after[..., c] - r[..., c])[judged[ch]].mean()) for c, ch in enumerate("rgb")}
    mae_before = {ch: float(np.abs(before[..., c] - r[..., c])[judged[ch]].mean()) for c, ch in enumerate("rgb")}
    intervals = _bootstrap(fit, model, r, sector, bootstrap, seed, leak, fitted_views) if bootstrap else {}
    standard_errors = None
    if taps is None:
        noise = model.prediction_variance(basis["variance"], fit.nl, fit.gains)
        noise = noise if image_variance is None else noise + np.asarray(image_variance, np.float64)
        standard_errors = tied_errors(fit.nl, ImageFitter(model, r, train, leak=leak).covariance(fit.nl, noise))
    r2_interval = {ch: heldout_interval(after[..., c], r[..., c], judged[ch], sector, seed) for c, ch in enumerate("rgb")}
    fast_table, fast_path = fit_fast_background(r, circle, camera, train, test, clipped, judged, sector, seed)
    tie = taps is None and not camera_known  # a held rotation is reported as held
    nl = fit.nl.tied() if tie else dataclasses.replace(
        fit.nl, rotation_rad=math.remainder(fit.nl.rotation_rad, 2 * math.pi))
    data = "one no-contact image" if taps is None else f"one no-contact image and {len(taps.ids)} taps"
    # each LED's own values: its unit's, and its turn from where the spec has it
    led_azimuth = tuple(float(nl.led_azimuth_rad[u] + ((nl.span_rad[u] - spans[u]) * o if spans else 0.0))
                        for u, o in zip(unit, share_of_span))
    profile = Profile(
        sensor=spec.name, leds=tuple(led.name for led in spec.leds),
        alignment=Alignment(nl.rotation_rad, nl.scale, nl.shift_px, led_azimuth, distortion=(nl.k1, camera.k2)),
        camera=CameraProfile(gamma=nl.gamma, offset=tuple(np.clip(fit.offset, 0.0, 1.0)),
                             saturation=tuple(CLIP_LEVEL if saturated[ch] else 1.0 for ch in "rgb"),
                             vignetting=nl.vignetting, image_circle=circle),
        reference={"effects": {**point, "coating_albedo": Effects().coating_albedo},
                   "led_leak": [nl.leak[u] for u in unit], "led_gains": fit.gains[unit].tolist(), "film": [width, height],
                   "photons": photons,
                   "spp": spp, "passes": passes, "seed": seed},
        phong={"ambient": 1.0, "background": fast_table},
        fit={"data": data, "converged": fit.converged, "heldout_r2": heldout, "camera_known": camera_known,
             "phong_heldout_r2": fast_path["heldout_r2"], "camera": fitted_camera(nl, camera)})
    report = {
        "converged": fit.converged, "loss": fit.loss, "start_loss": fit.start_loss, "evaluations": fit.evaluations,
        "heldout_r2": heldout, "heldout_r2_interval": r2_interval, "heldout_r2_before": heldout_before, "heldout_mae": mae,
        "heldout_mae_before": mae_before, "saturated": saturated, "clipped_share": dict(zip("rgb", share)),
        "image_circle": circle, "film": [width, height], "sectors": SECTORS,
        "split": "even angular sectors of the image circle fit, odd ones judge",
        "grid": [{"effects": p, "loss": f.loss, "noise": f.noise, "converged": f.converged} for f, p, _, _ in fits],
        "reweighting": reweighting,
        "best_effects": point, "parameters": _parameters(fit, tie=tie, spec=spec), "intervals": intervals,
        "gains": "each LED's power times its film response times each channel's white balance" if spectral_gains
        else "a free gain per LED and channel",
        "camera_response": (f"held to a webcam's (exponent {WEBCAM_GAMMA[0]:g} to {WEBCAM_GAMMA[1]:g}, black level "
                            f"at most {WEBCAM_BLACK:g})") if webcam
        else f"free (exponent {GAMMA_BOUNDS[0]:g} to {GAMMA_BOUNDS[1]:g}, any offset)",
        "standard_errors": standard_errors,
        "camera": fitted_camera(nl, camera), "on_bound": on_bound(fit.nl, model, leak),
        "not_identifiable": NOT_IDENTIFIABLE if taps is None else NOT_IDENTIFIABLE_WITH_TAPS, "fast_path": fast_path,
        "taps": tap_report,
    }
    if taps is not None and fit.converged and fast_path_fit is not None:
        chosen = taps if fast_taps is None else fast_taps
        table, report["fast_path"]["taps"] = fast_path_fit(spec, mesh, camera, profile, chosen, real)
        fitted = split(len(chosen.ids))
        report["fast_path"]["taps"]["ids"] = {"fitted": [i for i, f in zip(chosen.ids, fitted) if f],
                                              "judged": [i for i, f in zip(chosen.ids, fitted) if not f]}
        profile = dataclasses.replace(profile, phong={**profile.phong, **table})
    return Calibration(profile, report, {"real": r, "before": before, "after": after, "fast_path": fast_path.pop("image"),
                                         "judged": np.stack([judged[ch] for ch in "rgb"], -1)})


#: What one no-contact image cannot separate, and how the fit ties it.
NOT_IDENTIFIABLE = [
    "LED power, LED spectrum under the camera's filters, white balance and coating albedo all scale a source's "
    "image per channel: fitted together as each LED's RGB gain (led_gains); the coating albedo is tied at its "
    "default",
    "the global rotation and the LED azimuths: only their sums are seen (alignment.rotation_rad + led_azimuth_rad); "
    "tied by giving the azimuth offsets zero mean, so where contacts appear (the membrane's turn) needs taps",
    "the lens' fall-off (vignetting) and the medium's radial transport (absorption, scattering) both shape the "
    "radial profile; the grid's effects are judged with the fall-off fitted for each",
    "the lens' focal length (alignment.scale) and its k1 trade against each other: an image fixes where the rays "
    "land across the image circle, not each of the two (on a blind sensor's formula images the fit put k1 half "
    "its range off with every ray within 3 px); the calibration benchmark scores the lens by where its rays land",
]


#: What one no-contact image and taps cannot separate.
NOT_IDENTIFIABLE_WITH_TAPS = [
    NOT_IDENTIFIABLE[0], NOT_IDENTIFIABLE[2], NOT_IDENTIFIABLE[3],
    "each LED's own azimuth about the ring: each LED lights the membrane nearly all round, so on the reference's "
    "images (scattering 50 per m) turning one LED by 0.15 rad changed the no-contact fit's loss by at most 6 %, "
    "with its minimum away from the truth, and fitted one by one with 10 taps they were no closer than zero "
    "(median error 0.57-0.70 of their range's half-width, where 0 scores 0.5); tied to one turn of the ring "
    "against the membrane (every azimuth equal), which the contacts' shading sees",
]


def fitted_camera(nl, camera: Camera) -> dict:
    """The real camera the fit found, as a spec's [camera] table states it (scenes.spec):
    vertical field of view (None where the lens folds before the frame's edge),
    principal point, lens (its image circle is the report's)."""
    lens = nl.alignment(0.0, camera.k2).lens(camera)
    fov = 2 * float(lens_angle(np.array((lens.height / 2) / lens.f), lens.k1, lens.k2, lens.projection))
    if not math.isfinite(fov):  # a barrel that folds before the frame's edge: no field of view to state
        fov = None
    return {"fov_y": fov, "fov_y_deg": None if fov is None else math.degrees(fov),
            "principal_point_px": [lens.cx, lens.cy], "distortion": [lens.k1, lens.k2], "projection": lens.projection}


#: Nonlinear parameters whose bounds are physical limits, not the search's: a leak
#: fraction in [0, 1], a lens that cannot brighten its edge (V(1) <= 1) or whose fall-off
#: has no negative term, an arc no wider than the ring.
PHYSICAL_LIMITS = ("leak", "edge_illumination", "quartic_share", "span_rad")


def on_bound(nl, model: ImageModel, leak: bool, tolerance: float = 1e-3) -> dict[str, list[str]]:
    """The searched nonlinear parameters that ended within ``tolerance`` of their range's
    width of a bound: ``search`` (a range the fit chose, which the issue asks be widened
    or explained) and ``physical`` (PHYSICAL_LIMITS: e.g. no leak at all)."""
    out = {"search": [], "physical": []}
    for name, value, (lo, hi) in zip(nl.names(), nl.vector(), model.bounds(leak and model.has_leak.any())):
        if hi > lo and name != "rotation_rad" and min(value - lo, hi - value) <= tolerance * (hi - lo):
            out["physical" if name.split("[")[0] in PHYSICAL_LIMITS else "search"].append(name)
    return out


def _parameters(fit: ImageFit, tie: bool = True, spec: SensorSpec | None = None) -> dict:
    """The fitted values as plain data, per unit (an LED, or an LED group); ``tie``: the
    rotation and azimuths tied (only one image: see NOT_IDENTIFIABLE), else the rotation
    only wrapped. With the ``spec`` of LED groups, each group's fitted arc too (its
    centre's turn against the membrane is the rotation plus its azimuth offset)."""
    nl = fit.nl.tied() if tie else dataclasses.replace(fit.nl, rotation_rad=math.remainder(fit.nl.rotation_rad,
                                                                                            2 * math.pi))
    out = {"rotation_rad": nl.rotation_rad, "led_azimuth_rad": list(nl.led_azimuth_rad), "led_leak": list(nl.leak),
           "scale": nl.scale, "shift_px": list(nl.shift_px), "vignetting": list(nl.vignetting), "gamma": nl.gamma,
           "led_gains": fit.gains.tolist(), "offset": fit.offset.tolist(), "k1": nl.k1}
    if nl.span_rad:
        out["arc_span_rad"] = list(nl.span_rad)
    if spec is not None and spec.led_groups:
        first = len(spec.leds) - sum(g.count for g in spec.led_groups)  # the single LEDs' units come first
        out["led_groups"] = {g.name: {"arc_centre_rad": g.arc_centre_rad + nl.led_azimuth_rad[first + i],
                                      "arc_span_rad": nl.span_rad[first + i]} for i, g in enumerate(spec.led_groups)}
    return out


def _bootstrap(fit: ImageFit, model: ImageModel, r: np.ndarray, sector: np.ndarray, count: int, seed: int,
               leak: bool, taps: list[TapView] = ()) -> dict:
    """5-95 % intervals of each parameter over refits on resampled training sectors (and
    fitted taps, drawn with replacement too)."""
    rng = np.random.default_rng(seed)
    even = np.arange(0, SECTORS, 2)
    samples: dict[str, list] = {}
    for _ in range(count):
        drawn = np.bincount(rng.choice(even, len(even)), minlength=SECTORS)
        weight = drawn[sector].astype(np.float64)
        times = np.bincount(rng.choice(len(taps), len(taps)), minlength=len(taps)) if taps else []
        views = [dataclasses.replace(view, weight=float(n)) for view, n in zip(taps, times)]
        refit = ImageFitter(model, r, weight > 0, weight=weight, leak=leak, taps=views,
                            common_turn=bool(taps)).fit(fit.nl, max_evaluations=300)
        for name, value in _parameters(refit, tie=not taps and not model.known_alignment).items():
            samples.setdefault(name, []).append(np.asarray(value, np.float64))
    return {name: np.apply_along_axis(percentile_interval, 0, np.stack(values)).tolist() for name, values in samples.items()}


def _uncalibrated(rendered: SensorSpec, model: ImageModel, r, train) -> np.ndarray:
    """The reference with its default effects (``model`` of a basis rendered with them,
    of the LEDs ``rendered``: see ``basis_layout``), its LEDs where the spec has them,
    mapped to the real image by the best affine map per channel on the training pixels
    (what uncalibrated means here)."""
    default = Effects()
    from .render import source_response
    from .scene import led_sources

    response = source_response(led_sources(rendered, default), default)
    linear = model.warped(model.start()) @ response
    out = np.zeros_like(r)
    for c in range(3):
        x, y = linear[..., c][train], r[..., c][train]
        a, b = np.polyfit(x, y, 1)
        out[..., c] = np.clip(a * linear[..., c] + b, 0.0, 1.0)
    return np.where(model.inside[..., None], out, 0.0)


def calibrate_fast(real: np.ndarray, spec: SensorSpec, mesh, camera: Camera, taps, fast_path_fit,
                   seed: int = 0) -> Calibration:
    """The fast path alone, calibrated to a unit: its background term fitted to the real
    no-contact image (H, W, 3) on the even sectors and judged on the odd ones, as
    :func:`calibrate_background` fits it, and its LED constants fitted to the taps
    (``fast_path_fit``, as there); no render of the reference, so in seconds.

    The profile's alignment is the identity (the spec's camera: a capture whose contacts
    were placed by its own camera, as an imported set's are, needs no other), its camera
    the defaults and its ``reference`` table empty: the reference cannot render it.
    """
    real = check_real(real, camera, "the real no-contact image")
    if taps is None or fast_path_fit is None:
        raise ValueError("calibrate_fast fits the fast path's LED constants to taps: give taps and fast_path_fit")
    circle = image_circle(real)
    centre = (camera.cx, camera.cy) if circle is None else circle[:2]
    sector = sector_index(real.shape[:2], centre)
    inside = camera.mask
    train, test = (sector % 2 == 0) & inside, (sector % 2 == 1) & inside
    clipped = real >= CLIP_LEVEL
    judged = {ch: test & ~clipped[..., c] for c, ch in enumerate("rgb")}
    fast_table, fast_path = fit_fast_background(real, circle, camera, train, test, clipped, judged, sector, seed)
    image = fast_path.pop("image")
    profile = Profile(sensor=spec.name, leds=tuple(led.name for led in spec.leds),
                      camera=CameraProfile(image_circle=circle),
                      phong={"ambient": 1.0, "background": fast_table},
                      fit={"data": f"one no-contact image and {len(taps.ids)} taps, the fast path alone",
                           "converged": True, "phong_heldout_r2": fast_path["heldout_r2"]})
    table, fast_path["taps"] = fast_path_fit(spec, mesh, camera, profile, taps, real)
    fitted = split(len(taps.ids))
    fast_path["taps"]["ids"] = {"fitted": [i for i, f in zip(taps.ids, fitted) if f],
                                "judged": [i for i, f in zip(taps.ids, fitted) if not f]}
    profile = dataclasses.replace(profile, phong={**profile.phong, **table})
    heldout = fast_path["heldout_r2"]
    mae = fast_path["heldout_mae"]
    report = {
        "converged": True, "renderers": ["phong"], "loss": float("nan"), "start_loss": float("nan"),
        "heldout_r2": heldout, "heldout_r2_before": fast_path["solid"]["heldout_r2"], "heldout_mae": mae,
        "heldout_mae_before": fast_path["solid"]["heldout_mae"],
        "saturated": {ch: float(clipped[..., c][inside].mean()) > SATURATED_SHARE for c, ch in enumerate("rgb")},
        "image_circle": circle, "sectors": SECTORS,
        "split": "even angular sectors of the image fit the background term, odd ones judge; the capture's even "
                 "samples fit the LED constants, its odd ones judge",
        "best_effects": {}, "not_identifiable": ["the reference: not calibrated (--fast-only)"],
        "fast_path": fast_path, "what": "the fast path alone: its background term (before: the best solid colour) "
                                        "and its LED constants per light field",
    }
    judged_image = np.stack([judged[ch] for ch in "rgb"], -1)
    return Calibration(profile, report, {"real": real, "before": np.where(
        inside[..., None], [real[..., c][train].mean() for c in range(3)], 0.0), "after": image,
        "fast_path": image, "judged": judged_image})
