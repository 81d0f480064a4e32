"""The fast path as a dataset renderer plugin (entry point ``tactile_sim.renderers``).

A ``scenes.renderers.RendererPlugin`` that also ``Calibrates`` (``calibrate``, the fit of
the fast path's LED constants to a unit's taps); it shares no inputs with its workers.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from scenes.camera import CONTACT_EPS_M, Camera
from scenes.elastic import MembraneLayer, check_model
from scenes.elastic_solid import BondedLayer
from scenes.spec import SensorSpec

from .background import make_background
from .bake import METHODS, bake, field_method
from .render import Renderer, light_vectors

#: The dataset's ``source`` (scenes.dataset.SOURCES) for this renderer.
SOURCE = "sim"
#: The options this renderer takes.
OPTIONS = ("field", "background", "rectify", "elastic", "profile")


def options_from(options: dict) -> dict:
    unknown = sorted(set(options) - set(OPTIONS))
    if unknown:
        raise ValueError(f"the phong renderer takes no option {', '.join(unknown)}; its options are "
                         f"{', '.join(OPTIONS)}")
    field = options.get("field", "plane")
    if field not in METHODS:
        raise ValueError(f"field must be one of {METHODS}, got {field!r}")
    profile = options.get("profile")
    if profile is not None and "background" in options:
        raise ValueError("the phong renderer takes a background or a profile, not both: the profile's background "
                         "term is the calibrated unit's (phong.background)")
    background = str(options.get("background", "none"))
    # The published smoothing, or the layer model: the surface the reference renders.
    elastic = check_model(options.get("elastic", "published"), "elastic")
    if "elastic" not in options and profile is not None:
        elastic = None  # the profile's (phong.elastic), else the published smoothing: see make_layer
    return {"field": field, "background": background, "rectify": bool(options.get("rectify", False)),
            "elastic_model": elastic, "profile": None if profile is None else str(profile)}


def unit_spec(spec: SensorSpec, opts: dict):
    """(the spec the fields are baked for, the Profile or None) of validated options: the
    profile's unit, its LEDs where the profile placed them for the field."""
    if opts["profile"] is None:
        return spec, None
    from scenes.profile import load_profile

    from .profiled import profile_constants

    profile = load_profile(opts["profile"], spec)
    return profile_constants(profile, profile.sensor_spec(spec), opts["field"]), profile


def prepare(spec: SensorSpec, mesh, camera: Camera, options: dict) -> dict:
    """Bake what the renderer needs (cached on disk) and return its settings."""
    opts = options_from(options)
    unit, profile = unit_spec(spec, opts)
    bake(mesh, camera, unit.leds, opts["field"])
    if profile is None:
        make_background(opts["background"], camera)  # fail early on a bad image
        return {"renderer": "phong", **opts, "elastic": dataclasses.asdict(spec.elastic)}
    from .profiled import profile_background

    profile_background(profile, camera)  # fail early on a profile without the fast path's table
    return {"renderer": "phong", **opts, "background": "profile", "profile_data": profile.to_dict(),
            "elastic": dataclasses.asdict(spec.elastic)}


class PhongDatasetRenderer:
    """Depth map -> tactile image with the fast path, for dataset generation."""

    def __init__(self, spec: SensorSpec, mesh, camera: Camera, ref_depth: np.ndarray, options: dict):
        opts = options_from(options)
        unit, profile = unit_spec(spec, opts)
        fields = bake(mesh, camera, unit.leds, opts["field"])
        layer = make_layer(opts["elastic_model"], profile, spec, mesh, camera)
        L = light_vectors(fields, opts["rectify"])
        if profile is None:
            self._renderer = Renderer(spec, camera, ref_depth, L, make_background(opts["background"], camera), layer)
        else:
            from .profiled import ProfiledRenderer

            self._renderer = ProfiledRenderer(spec, ref_depth, L, profile, layer, field=opts["field"])
        self.ref_depth = self._renderer.ref_depth

    @property
    def no_contact(self) -> np.ndarray:
        return self._renderer.base

    def render(self, depth: np.ndarray) -> np.ndarray:
        depth = np.asarray(depth, dtype=np.float32)
        depth = np.where(np.abs(depth - self.ref_depth) <= CONTACT_EPS_M, self.ref_depth, depth)
        return self._renderer.render(depth)


def elastic_layer(entry: dict, spec: SensorSpec, camera: Camera) -> BondedLayer:
    """The dent a profile's ``phong.elastic`` entry names: ``{"model": "bonded",
    "thickness_m", "poisson_ratio"}``; ValueError naming a malformed entry."""
    try:
        model, thickness, poisson = entry["model"], float(entry["thickness_m"]), float(entry["poisson_ratio"])
    except (KeyError, TypeError, ValueError):
        raise ValueError(f"profile phong.elastic must hold model, thickness_m and poisson_ratio, got {entry!r}") from None
    if model != "bonded":
        raise ValueError(f"profile phong.elastic.model must be 'bonded' (a layer with physical parameters), got "
                         f"{model!r}")
    return BondedLayer(spec, camera, thickness, poisson)


def make_layer(model: str | None, profile, spec: SensorSpec, mesh, camera: Camera):
    """The elastic model's dent for the renderer: ``model`` by name (scenes.elastic.MODELS),
    or None: the profile's ``phong.elastic`` where it has one, else the published smoothing
    (no layer)."""
    if model is None:
        entry = None if profile is None else profile.phong.get("elastic")
        return None if entry is None else elastic_layer(entry, spec, camera)
    return {"layer": lambda: MembraneLayer(mesh, spec, camera), "bonded": lambda: BondedLayer(spec, camera),
            "published": lambda: None}[model]()


def make_renderer(spec, mesh, camera, ref_depth, options) -> PhongDatasetRenderer:
    return PhongDatasetRenderer(spec, mesh, camera, ref_depth, options)


#: The published smoothing's Gaussian the calibration searches, as shares of the spec's
#: (``Elastic.sigma_px``: how far a contact's dent spreads, the elastomer's decay length).
SIGMA_SCALES = (0.35, 0.5, 0.7, 1.0, 1.4)


def calibrate(spec: SensorSpec, mesh, camera: Camera, profile, taps, background: np.ndarray,
              fields=METHODS, elastic: dict | None = None) -> tuple[dict, dict]:
    """The fast path's LED constants from a unit's taps (``phong_reference.calibrate``), with
    each light field of ``fields`` baked for the profile's LEDs: (entries of the profile's
    ``phong`` table, the report). Each field gets its own constants (``phong.fields``),
    its own spread of the dent (the published smoothing's Gaussian, searched over
    SIGMA_SCALES of the spec's: ``sigma_px``) and, for a field whose light leaves each
    LED's own place, the LEDs' places (``positions``, ``fit_led_places``); each choice
    is the one that fits the fitted taps best. The top-level ``leds`` and ``shininess``
    are those of the field that fits the fitted taps best (the lowest MAE of their
    change over their contact regions), and the profile composes by change
    (``phong_reference.profiled``).

    ``elastic``: the dent of an elastic model with physical parameters instead of the
    published smoothing (``elastic_layer``: ``{"model": "bonded", "thickness_m",
    "poisson_ratio"}``, as ``phong_reference.elastic_fit`` fits it); no spread is searched,
    and the table records it (``elastic``), so that the profile renders with it."""
    from .calibrate import fit_led_constants, fit_led_places

    physical = None if elastic is None else dict(elastic)  # the name ``elastic`` is the spread's below
    layer = None if physical is None else elastic_layer(physical, spec, camera)

    def fit_loss(report: dict) -> float:
        return float(np.mean(list(report["fit"]["mae"].values())))

    def spreads(L):
        out = {}
        if layer is not None:  # a physical dent has no published spread to search
            return {1.0: (spec.elastic, *fit_led_constants(spec, camera, taps.ref_depth, L, profile, taps, background,
                                                            layer))}
        for scale in SIGMA_SCALES:
            sigma = spec.elastic.sigma_px * scale
            elastic = dataclasses.replace(spec.elastic, sigma_px=sigma, radius_px=max(1, int(round(3 * sigma))))
            out[scale] = (elastic, *fit_led_constants(spec.replace(elastic=elastic), camera, taps.ref_depth, L,
                                                      profile, taps, background))
        return out

    by_field, reports = {}, {}
    for field in fields:
        leds, places = profile.sensor_spec(spec).leds, None
        free = field_method(field).free_sources  # its light leaves each LED's own place
        if free:
            positions, places = fit_led_places(spec, mesh, camera, profile, taps, background, field, layer)
            leds = tuple(dataclasses.replace(led, position=p) for led, p in zip(leds, positions))
        spread = spreads(light_vectors(bake(mesh, camera, leds, field)))
        scale = min(spread, key=lambda k: fit_loss(spread[k][2]))
        if free and scale != 1.0:  # the places again, with the dent's spread they fit best with
            positions, places = fit_led_places(spec.replace(elastic=spread[scale][0]), mesh, camera, profile, taps,
                                               background, field)
            leds = tuple(dataclasses.replace(led, position=p) for led, p in zip(profile.sensor_spec(spec).leds,
                                                                                  positions))
            spread = spreads(light_vectors(bake(mesh, camera, leds, field)))
            scale = min(spread, key=lambda k: fit_loss(spread[k][2]))
        elastic, by_field[field], reports[field] = spread[scale]
        by_field[field]["sigma_px"], by_field[field]["radius_px"] = elastic.sigma_px, elastic.radius_px
        reports[field]["spread"] = {"sigma_px": elastic.sigma_px, "share_of_the_spec": scale,
                                    "fit_mae_by_share": {str(k): fit_loss(v[2]) for k, v in spread.items()}}
        if places is not None:
            by_field[field]["positions"] = [list(p) for p in positions]
            # the same fit with the LEDs where the unit has them, and the spec's constants there ("before")
            unmoved = fit_led_constants(spec, camera, taps.ref_depth,
                                        light_vectors(bake(mesh, camera, profile.sensor_spec(spec).leds, field)),
                                        profile, taps, background, layer)[1]
            reports[field]["heldout_before"] = unmoved["heldout_before"]
            reports[field]["places"] = {**places, "heldout_at_the_units_places": unmoved["heldout"]}
    best = min(fields, key=lambda f: fit_loss(reports[f]))
    table = {**by_field[best], "field": best, "fields": by_field, "composition": "change",
             **({"elastic": physical} if physical is not None else {})}
    return table, {**reports[best], "field": best, "by_field": reports,
                   "chosen": "the field whose constants fit the fitted taps' changes best (mean MAE over channels)"}
