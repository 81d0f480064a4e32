"""Per-source basis images of the reference, cached: the images the calibration fits.

The reference's image is linear in each source's power and its transport is grey, so one
grey image per source (each LED, and each LED's leak into the glass core) per unit flux
stands for every set of LED powers and colours.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from scenes.camera import Camera
from scenes.spec import SensorSpec

from .effects import Effects
from .reweight import PARAMETERS, Perturbation, valid

#: Effects the basis is rendered with besides the grid's: the leak sources exist (their
#: power is fitted) and the coating albedo is tied (it scales every source like a power).
BASIS_EFFECTS = {"core_light_leak": 0.5}
#: A no-contact basis is rendered this much wider than the spec's camera (its focal
#: length over this), so that a fitted lens that sees wider than the spec's (an image
#: scale down to 1 / BASIS_WIDER, a barrel) still reads rendered pixels.
BASIS_WIDER = 1.3


def basis_camera(camera: Camera) -> Camera:
    """The camera a no-contact basis is rendered with: ``camera``'s lens, its focal
    length over BASIS_WIDER."""
    return dataclasses.replace(camera, f=camera.f / BASIS_WIDER)


def emitter_basis(spec: SensorSpec, mesh, camera: Camera, effects: Effects, film: tuple[int, int],
                  photons: int = 1 << 18, spp: int = 32, passes: int = 2, seed: int = 0,
                  use_cache: bool = True, depth: np.ndarray | None = None,
                  ref_depth: np.ndarray | None = None, solids=None, no_contact_runs: int = 0,
                  inscatter: str = "fluence", perturb=None, only=None) -> dict:
    """One grey image per source (``pbr_tactile.scene.led_sources``, with leaks) of the
    sensor: ``mean`` (h, w, S) per unit flux, ``variance``, ``names`` (S,), ``response``
    (S, 3) the film's response to each source at the effects' powers. Without ``depth``
    the no-contact sensor; with a contact depth map (H, W) m and the no-contact
    ``ref_depth``, that contact (the same seed as the no-contact basis: common random
    numbers, so their difference is the contact's change with little noise). Cached on
    disk (scenes.cache) by everything it depends on. ``solids``: the membrane's
    ``ElastomerBuilder`` for this spec and camera, kept across renders (it refines and
    checks the membrane once; None builds one). ``no_contact_runs``: the photon map as the
    sensor's cached no-contact map (this many runs per pass) plus the contact's change, as
    a dataset renders it (``pbr_tactile.render.reference``); 0 traces every photon each time.
    ``inscatter``: how the camera finds the light the elastomer scatters towards it
    (``reference``'s; the fluence lookup by default, as every reference render).

    ``perturb``: a ``pbr_tactile.reweight.Perturbation`` or its (K, 3) array of variants
    (absorption_per_m, scattering_per_m, coating_albedo), each re-weighted from the same
    photons (``pbr_tactile.reweight``; a glossy paint's albedo is not). The dict then also holds
    ``perturb`` (K, 3), ``variant_mean`` and ``variant_variance`` (K, h, w, S), each
    variant's basis as ``mean`` and ``variance`` are the traced one's, ``ess_ratio`` (K, S)
    the variants' Kish effective-sample-size ratios and ``valid`` (K,) bool, those at
    ``pbr_tactile.reweight.MIN_ESS_RATIO`` or above for every source (the others: render
    them with their own effects instead). The identity part is cached under the key
    without variants too, so a later call without them reads it.

    ``only``: the places of the sources to render (``reference``'s): ``names``, ``mean``
    and the rest hold those, traced as they are in the whole basis (common random
    numbers), so they stand in for its columns where a change touches only them."""
    from scenes.cache import cached, make_key

    from .nocontact import CACHE_VERSION
    from .camera_pass import CAMERA_PASS_VERSION
    from .render import RenderSettings, reference, source_response
    from .scene import led_sources
    from .variant import choose_variant

    variant = choose_variant().variant()
    width, height = film
    if (depth is None) != (ref_depth is None):
        raise ValueError("emitter_basis: a contact needs both depth and ref_depth")
    contact = [] if depth is None else [np.asarray(depth, np.float32), np.asarray(ref_depth, np.float32)]
    own = camera == Camera.from_spec(spec)
    key = make_key("basis", 2, CACHE_VERSION, CAMERA_PASS_VERSION, variant, inscatter, dataclasses.asdict(spec),
                   np.asarray(mesh.vertices), effects.to_dict(), [width, height], photons, spp, passes, seed, *contact,
                   *([no_contact_runs] if no_contact_runs else []), *([] if own else [dataclasses.asdict(camera)]),
                   *([] if only is None else ["only", [int(k) for k in only]]))
    perturbation = None if perturb is None else Perturbation.of(perturb)
    sources = led_sources(spec, effects)

    def identity(est) -> dict:  # after the render, which checks ``only``
        chosen = sources if only is None else [sources[int(k)] for k in only]
        return {"mean": est.mean, "variance": est.variance, "names": np.array([s["name"] for s in chosen]),
                "response": source_response(chosen, effects)}

    def render(perturb_=None):
        settings = RenderSettings(spp=spp * passes, width=width, height=height, seed=seed, variant=variant,
                                  passes=passes, photons=photons, no_contact_runs=no_contact_runs, per_source=True,
                                  inscatter=inscatter)
        return reference(depth, ref_depth, mesh, spec, camera, effects, settings, perturb=perturb_, solids=solids,
                         only=only)

    if perturbation is None:
        return cached("pbr-calibration-basis", key, lambda: identity(render()), use_cache=use_cache)

    def build_variants():
        est = render(perturbation)
        out = identity(est.traced)
        out.update({"perturb": perturbation.values.copy(),
                    "variant_mean": np.stack([e.mean for e in est.variants]),
                    "variant_variance": np.stack([e.variance for e in est.variants]),
                    "ess_ratio": est.ess_ratio})
        return out

    arrays = cached("pbr-calibration-basis", make_key(key, "perturb", perturbation.key()), build_variants,
                    use_cache=use_cache)
    # The identity as a render without variants would have cached it (the same walks).
    cached("pbr-calibration-basis", key, lambda: {k: arrays[k] for k in ("mean", "variance", "names", "response")},
           use_cache=use_cache)
    return {**arrays, "valid": valid(arrays["ess_ratio"])}


def grid_bases(points: list[dict], base: Effects, basis_at) -> tuple[list[dict], dict | None]:
    """Each grid point's basis, ``basis_at(effects, perturb=None)`` (``emitter_basis`` with
    the rest bound), from as few traces as it can: where every point differs from ``base``
    only in the medium and the paint's albedo (``reweight.PARAMETERS``; a glossy paint's
    albedo not), one basis is traced at the grid's middle point (each parameter's median value,
    else the point nearest it) and re-weighted to every other point (perturbation Monte
    Carlo); a point whose re-weighting is not valid (``reweight.MIN_ESS_RATIO``) is traced
    again with its own effects. Returns (bases in the points' order, a report of what was
    traced and re-weighted, or None where each point was traced)."""
    glossy_albedo = base.coating_gloss > 0 and any(float(p.get("coating_albedo", base.coating_albedo))
                                                   != base.coating_albedo for p in points)
    if len(points) < 2 or glossy_albedo or any(k not in PARAMETERS for p in points for k in p):
        return [basis_at(dataclasses.replace(base, **p)) for p in points], None
    values = np.array([[float(p.get(k, getattr(base, k))) for k in PARAMETERS] for p in points])
    # a walk represents the others only where it scatters and its paint reflects, if any of theirs do
    able = np.all((values[:, [1, 2]] > 0) | ~np.any(values[:, [1, 2]] > 0, axis=0), axis=1)
    if not able.any():
        return [basis_at(dataclasses.replace(base, **p)) for p in points], None
    middle = np.median(values, axis=0)
    spread = np.ptp(values, axis=0)
    spread[spread == 0] = 1.0
    traced = int(np.argmin(np.where(able, np.abs((values - middle) / spread).sum(axis=1), np.inf)))
    basis = basis_at(dataclasses.replace(base, **points[traced]), perturb=values)
    keys = ("mean", "variance", "names", "response")
    out, retraced, reweighted = [], {}, []
    for k, point in enumerate(points):
        label = ", ".join(f"{name}={v:g}" for name, v in point.items())
        if k == traced:
            out.append({key: basis[key] for key in keys})
        elif basis["valid"][k]:
            out.append({"mean": basis["variant_mean"][k], "variance": basis["variant_variance"][k],
                        "names": basis["names"], "response": basis["response"]})
            reweighted.append(label)
        else:
            out.append(basis_at(dataclasses.replace(base, **point)))
            retraced[label] = float(np.min(basis["ess_ratio"][k]))
    return out, {"traced": points[traced], "reweighted": reweighted, "retraced": retraced,
                 "what": "the grid's bases: one traced at the middle point and re-weighted to the others "
                         "(pbr_tactile.reweight); retraced: the points whose Kish ESS ratio (the least over "
                         "sources, given) fell below reweight.MIN_ESS_RATIO, traced again"}


def is_leak(names) -> np.ndarray:
    """(S,) bool: which sources (``led<m>`` or ``led<m>_leak``) are an LED's leak into the core."""
    return np.array([str(n).endswith("_leak") for n in names], bool)


def led_of_source(names) -> np.ndarray:
    """(S,) the LED index of each source name (``led<m>`` or ``led<m>_leak``)."""
    return np.array([int(str(n)[3:].split("_")[0]) for n in names])


def basis_layout(spec: SensorSpec) -> tuple[SensorSpec, list | None, tuple, np.ndarray, np.ndarray]:
    """How the basis renders a spec's LEDs: the spec it renders (its single LEDs, then
    one LED of each group's build at the arc's centre: a group's LEDs differ only by a
    turn about the axis, which the rotationally symmetric membrane turns into an image
    rotation, so one render per group stands for all of them), each unit's arc offsets
    (``LEDGroup.offsets``; None without groups) and span (rad; () without groups), and
    for each of ``spec.leds`` its unit (L,) and its offset along the arc (L,) as a share
    of the span."""
    if not spec.led_groups:
        return spec, None, (), np.arange(len(spec.leds)), np.zeros(len(spec.leds))
    singles = [led for led in spec.leds if led.group is None]
    groups = list(spec.led_groups)
    rendered = singles + [g.led_at(g.arc_centre_rad, g.name) for g in groups]
    arcs = [np.zeros(1)] * len(singles) + [g.offsets() for g in groups]
    spans = (0.0,) * len(singles) + tuple(g.arc_span_rad for g in groups)
    place = {led.name: (i, 0.0) for i, led in enumerate(singles)}
    for g, group in enumerate(groups):
        place.update({led.name: (len(singles) + g, float(o)) for led, o in zip(group.leds(), group.offsets())})
    unit, share = zip(*(place[led.name] for led in spec.leds))
    return spec.replace(leds=tuple(rendered), led_groups=()), arcs, spans, np.array(unit), np.array(share)
