"""The physical candidates of a reference-rendered simulation: what the diagnosis can fit
when the physically based reference rendered the simulated dataset.

When the simulated dataset was rendered by the reference (``source: "pbr"``), the
candidate effects are the reference's own switches (``physical_catalogue``):

- every field of ``pbr_tactile.effects.Effects``, so that new physics joins without
  edits here (a field this module does not know is re-rendered on a grid of its range);
- the membrane's mechanics: the imprint's depth (``membrane_compliance``) and the elastic
  layer's spread (``layer_spread``, through the elastomer's Poisson ratio, which sets the
  layer's decay length, ``scenes.elastic.layer_length``);
- the LEDs' powers (``led_power``) and spectra (``led_peak_shift``);
- a calibrated unit's camera and alignment (``camera_gains``, ``alignment``, ``blur``:
  the fast catalogue's image models, ``FAST_MODELS``).

Each candidate has a kind (how the reference model evaluates it,
``studies.gap.reference_model``: linear in the per-source images, re-rendered on a grid,
on the image, or a fast image model), a grid where it is re-rendered (``GRIDS``), and a
counterpart in the fast catalogue (``COUNTERPARTS``).
"""

from __future__ import annotations

import dataclasses
import math

from scenes.spec import SensorSpec

from . import effects as fx

#: The capture's exposure, relative to the one the reference's rule gives it (the rule:
#: ``ReferenceModel.exposure``), fitted with every physical candidate. A real camera's
#: exposure is its own; a reference capture's is set by its own no-contact frame's
#: 99.5th percentile, which the basis, at its fewer photons and lower film, predicts only
#: to about 1 % (measured: the ratio of two leaks' gains moved from 1.009 to 1.037 with
#: the basis' seed at 2^16 photons), and 1 % of a bright image is as large as the change
#: a physical effect makes in a dim one. Where an effect makes a small bright spot, the
#: rule's percentile at the basis film falls far short of the capture's own: a leak of
#: 0.46 aimed up the tube in a cone of 0.3 rad, whose capture's gain was 16.6, was given
#: 23.8 by the rule at the true values (22.3 without the leak's smoothing), so the range
#: reaches to half and twice the rule's.
EXPOSURE = fx.Param("exposure", 0.5, 2.0, 1.0, "-", "the capture's exposure gain relative to the one the "
                    "reference's rule gives it")
#: Effects fields whose change is linear in the per-source images: no render.
LINEAR_FIELDS = ("core_light_leak", "led_spectra", "camera_response")
#: Effects fields that act on the rendered image (``pbr_tactile.sensor``).
IMAGE_FIELDS = ("vignetting", "lens_distortion")
#: Effects fields a mean prediction cannot hold, and why.
UNPREDICTABLE_FIELDS = {"sensor_noise": "noise is estimated from the residual (report 'noise'), not predicted: "
                                        "a prediction is a mean"}
#: Re-rendered candidates: the grid's ends and its interpolation (the simulation's own
#: value is always a grid point). A field of Effects not listed is searched over
#: ``DEFAULT_GRID_SPAN`` times its value (or its accepted range where that is finite).
#: "inner": more points between the ends, where one span of the medium's coefficients is
#: too wide to interpolate (with (20, 120) and (50, 250) only, a hidden scattering of 139
#: per m was fitted as 67 and ranked below absorption; a hidden albedo of 0.71, between
#: 0.6 and 0.85, as 0.65, and ranked below camera_gains). The compliance stops at 1.25:
#: on the real GelSight it was fitted at that end, and at 1.8 when the grid reached it,
#: but 1.8 pushes the 36-pair bench's deeper GelTip taps (1.5 mm) through the glass core
#: (the elastomer refuses the depth map); a top bounded by each capture's membrane is
#: still to do.
GRIDS = {
    "absorption_per_m": {"low": 5.0, "high": 120.0, "interpolation": "geometric", "unit": "1/m",
                         "doc": "absorption coefficient of the elastomer", "inner": (10.0, 50.0)},
    "scattering_per_m": {"low": 10.0, "high": 250.0, "interpolation": "geometric", "unit": "1/m",
                         "doc": "scattering coefficient of the elastomer", "inner": (22.0, 110.0)},
    "coating_albedo": {"low": 0.6, "high": 0.97, "interpolation": "linear", "unit": "-",
                       "doc": "diffuse reflectance of the coating", "inner": (0.72,)},
    "core_leak_cone_rad": {"low": 0.0, "high": 0.6, "interpolation": "linear", "unit": "rad",
                           "doc": "half-angle of the core leak's cone up the tube", "inner": (0.3,)},
    "membrane_compliance": {"low": 0.6, "high": 1.25, "interpolation": "linear", "unit": "-",
                            "doc": "imprint depth / commanded depth"},
    "layer_spread": {"low": 0.0, "high": 0.5, "interpolation": "linear", "unit": "-",
                     "doc": "Poisson ratio of the elastomer (the layer's decay length h sqrt((1 - nu) / 6))"},
}
DEFAULT_GRID_SPAN = 4.0
#: Image models borrowed from the fast catalogue (the unit's camera and alignment).
FAST_MODELS = {"camera_gains": "camera_response", "alignment": "misalignment", "blur": "blur_noise"}
#: Where each candidate acts.
STAGE_OF = {"membrane_compliance": "membrane", "layer_spread": "membrane", "led_power": "light",
            "led_peak_shift": "light", "vignetting": "optics", "lens_distortion": "optics", "alignment": "optics",
            "blur": "optics", "camera_gains": "sensor", "sensor_noise": "sensor"}
#: The fast catalogue's image-level or shading counterpart of each physical candidate.
#: The LEDs' spectra and the camera's spectral response change each LED's colour, which
#: for three LEDs is a 3x3 colour matrix on the linear image (``ReferenceModel.
#: colour_matrix``): the fast camera_response. (led_spectrum shifts peaks of one shape; on
#: flat-white LEDs hidden in a capture it closed 5 % where camera_response closed 87 %.)
COUNTERPARTS = {"core_light_leak": "core_light_leak", "core_leak_cone_rad": "core_light_leak",
                "absorption_per_m": "path_attenuation", "scattering_per_m": "path_attenuation",
                "coating_gloss": "coating_gloss", "coating_albedo": "camera_response",
                "contact_shadow": "contact_shadow", "led_spectra": "camera_response",
                "camera_response": "camera_response",
                "vignetting": "vignetting", "lens_distortion": "lens_distortion", "sensor_noise": "blur_noise",
                "membrane_compliance": "membrane_compliance", "layer_spread": "elastic_spread",
                "led_power": "led_spectrum", "led_peak_shift": "led_spectrum", "camera_gains": "camera_response",
                "alignment": "misalignment", "blur": "blur_noise"}


def _field_kind(field: dataclasses.Field, value) -> str:
    if field.name in UNPREDICTABLE_FIELDS:
        return "unpredictable"
    if field.name in LINEAR_FIELDS:
        return "linear"
    if field.name in IMAGE_FIELDS:
        return "image"
    return "render"


def _grid_for(name: str, identity: float) -> dict:
    """The grid of a re-rendered numeric candidate: ``values`` (sorted, through the
    identity), bounds, interpolation, unit and doc."""
    from pbr_tactile.effects import RANGES

    known = GRIDS.get(name)
    if known is None:
        low, high = RANGES.get(name, (0.0, math.inf))
        span_low = identity / DEFAULT_GRID_SPAN if identity > 0 else 0.0
        span_high = identity * DEFAULT_GRID_SPAN if identity > 0 else 1.0
        known = {"low": max(low, span_low), "high": min(high, span_high), "interpolation": "linear", "unit": "-",
                 "doc": f"Effects.{name}"}
    low, high = min(known["low"], identity), max(known["high"], identity)
    inner = [float(v) for v in known.get("inner", ()) if low < v < high]
    values = tuple(sorted({float(low), float(identity), float(high), *inner}))
    return {**known, "low": float(low), "high": float(high), "values": values}


def candidate_names() -> tuple[str, ...]:
    """Every candidate name of a reference-rendered simulation (``physical_catalogue``)."""
    from pbr_tactile.effects import Effects

    return (tuple(f.name for f in dataclasses.fields(Effects)) + ("membrane_compliance", "layer_spread", "led_power",
                                                                    "led_peak_shift") + tuple(FAST_MODELS))


def physical_catalogue(spec: SensorSpec, effects, sigma_px: float = 5.0) -> tuple[dict, dict, dict]:
    """The candidates of a reference-rendered dataset of sensor ``spec`` whose effects
    were ``effects`` (a ``pbr_tactile.effects.Effects``).

    Returns (catalogue {name: fx.Effect}, kinds {name: "linear" | "render" | "image" |
    "fast" | "unpredictable" | "bool-render"}, grids {name: grid} for re-rendered ones).
    """
    fast = fx.catalogue(len(spec.leds), sigma_px)
    leds = range(len(spec.leds))
    out, kinds, grids = {}, {}, {}

    def add(name: str, params, doc: str, kind: str) -> None:
        out[name] = fx.Effect(name, STAGE_OF.get(name, "light"), tuple(params), doc)
        kinds[name] = kind

    for field in dataclasses.fields(effects):
        name, value = field.name, getattr(effects, field.name)
        kind = _field_kind(field, value)
        doc = f"the reference's Effects.{name}"
        if kind == "unpredictable":
            add(name, (), doc, kind)
        elif isinstance(value, bool):
            add(name, (fx.Param("on", 0.0, 1.0, float(value), "-", f"{name} switched on (1) or off (0); between: "
                                "a blend of the two"),), doc, "bool-" + kind)
            if kind == "render":
                grids[name] = {"values": (0.0, 1.0), "interpolation": "linear", "low": 0.0, "high": 1.0}
        elif name == "core_light_leak":
            add(name, (fx.Param("fraction", 0.0, 1.0, float(value), "-", "share of each LED's power emitted into the "
                                "glass core"),), doc, kind)
        elif name == "core_leak_cone_rad" and not effects.core_light_leak:
            # No leak in the simulation, so no cone to shape: the candidate is a leak aimed up
            # the tube, with its own fraction (``ReferenceModel._light``).
            grid = _grid_for(name, float(value))
            grids[name] = grid
            add(name, (fx.Param("value", grid["low"], grid["high"], float(value), grid["unit"], grid["doc"]),
                       fx.Param("fraction", 0.0, 1.0, 0.0, "-", "share of each LED's power its core leak emits, in "
                                "the cone (the simulation has no leak; core_light_leak's where both are fitted)")),
                doc, kind)
        elif name == "vignetting":
            add(name, (fx.Param("strength", 0.0, 0.9, float(value), "-", "relative fall-off at the image circle's "
                                "edge, 1 - strength (r / R)^2"),), doc, kind)
        elif name == "lens_distortion":
            add(name, (fx.Param("k1", -0.5, 0.5, float(value[0]), "-", "radial coefficient of r^2"),
                       fx.Param("k2", -0.3, 0.3, float(value[1]), "-", "radial coefficient of r^4")), doc, kind)
        elif isinstance(value, (int, float)):
            grid = _grid_for(name, float(value))
            grids[name] = grid
            add(name, (fx.Param("value", grid["low"], grid["high"], float(value), grid["unit"], grid["doc"]),),
                doc, kind)
        else:  # a new kind of field (a pair, a string): named, not fitted
            add(name, (), doc, "unpredictable")
    for name, identity in (("membrane_compliance", 1.0), ("layer_spread", float(spec.elastic.poisson_ratio))):
        grid = _grid_for(name, identity)
        grids[name] = grid
        add(name, (fx.Param("value", grid["low"], grid["high"], identity, grid["unit"], grid["doc"]),),
            GRIDS[name]["doc"], "render")
    add("led_power", [fx.Param(f"power_{m}", 0.3, 3.0, 1.0, "-", f"LED {m}'s relative power") for m in leds],
        "each LED's power", "linear")
    add("led_peak_shift", [fx.Param(f"shift_nm_{m}", -30.0, 30.0, 0.0, "nm", f"LED {m}'s peak shift") for m in leds],
        "each LED's emission peak against the camera's filters", "linear")
    for name, fast_name in FAST_MODELS.items():
        e = fast[fast_name]
        params = e.params
        if fast_name == "misalignment":  # the reference draws no image circle: the whole frame moves
            params = tuple(dataclasses.replace(p, low=1.0, high=1.0, identity=1.0) if p.name == "frame_share" else p
                           for p in params if p.name != "frame_share")
        add(name, params, f"the unit's {fast_name.replace('_', ' ')} ({e.doc})", "fast")
    # every physical candidate is fitted with the capture's exposure
    out = fx.with_exposure(out, EXPOSURE, tuple(n for n, k in kinds.items() if k not in ("fast", "unpredictable")
                                                and out[n].params))
    return out, kinds, grids
