"""Inject unmodelled physical effects into fast-path renders: the gap benchmark's injector.

The sim-to-real gap diagnosis gets a "real" and a "simulated" dataset of the same
tapping protocol and must name the physical effect that makes them differ. To test it
blind, the benchmark makes fake "real" datasets: it renders the simulator's own contacts
with one or two hidden effects injected here at a random strength, and the simulated
counterpart without. This module models each effect physically, in its own way and with
its own code, and never imports the diagnosis' effect models: a benchmark that shared
them would pass by construction.

Every injected render is the fast path (``phong_reference.render``) with the effect put
where it acts physically, in this order whatever the order given:

1. membrane: ``membrane_compliance`` (a shallower imprint), ``elastic_spread`` (another
   smoothing width);
2. light transport and shading, per LED: ``coating_gloss``, ``led_spectrum`` (other
   Phong constants and colours), ``path_attenuation`` (absorption along the geodesic
   path), ``contact_shadow`` (the imprint's rim occludes the guided light),
   ``core_light_leak`` (LED light crossing the glass core);
3. background, clipping and the sensor's circle mask, as the fast path does;
4. optics: ``misalignment``, ``lens_distortion``, ``vignetting``, then the blur of
   ``blur_noise``;
5. sensor: ``camera_response``, then the noise of ``blur_noise``; a last clip to [0, 1].

``Injector(spec).sample(effect, rng)`` draws an :class:`Injection` (strength in [0, 1]
mapped to physical parameters, from weak but clearly visible to strong) and
``Injector.render(depth, injections, rng)`` renders it. The lower-level functions below
are arrays in, arrays out; ``Injector`` only holds what does not depend on the contact.

What an effect can show depends on the contact, as it would on a real sensor. With the
tangent light fields and no background, only the contact itself is lit, so:

* ``vignetting`` and ``lens_distortion`` barely touch a contact on the optical axis (a
  2 mm contact 140 px off the axis changes by 0.04 at strength 0);
* ``contact_shadow`` needs something to shadow: the fast path lights only slopes that
  face an LED, and a single convex imprint (sphere, cone, cylinder) puts nothing between
  such a slope and its LED. Multi-feature contacts (dots, textures, prisms) and a
  background (which stands for the no-contact guided light, so it is shadowed too)
  show it.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from phong_reference.background import check_background, make_background
from phong_reference.bake import METHODS, bake
from phong_reference.normals import normals
from phong_reference.render import Renderer, finish, light_vectors
from phong_reference.sources import snap_leds
from scenes.camera import CONTACT_EPS_M, Camera, back_project, cast_rays, check_depth
from scenes.elastic import deform
from scenes.geometry import membrane_mesh
from scenes.spec import Elastic, SensorSpec
from studies.gap.inject_image import add_noise, blur, distort, misalign, respond, vignette
from studies.gap.inject_light import (SHADOW_SOFT_ELEVATIONS, core_leak, deformed_grid, gloss, led_layers,
                                     shadow_visibility, shift_spectra, transmittance)

EFFECTS: tuple[str, ...] = (
    "core_light_leak", "path_attenuation", "membrane_compliance", "elastic_spread",
    "coating_gloss", "contact_shadow", "camera_response", "vignetting", "lens_distortion", "misalignment",
    "blur_noise", "led_spectrum",
)

#: Effects that change the membrane or its shading, so the image is shaded again.
SHADED_EFFECTS = frozenset({
    "membrane_compliance", "elastic_spread", "path_attenuation", "core_light_leak", "contact_shadow",
    "coating_gloss", "led_spectrum",
})

# Strength maps linearly from the first value (strength 0, weak but clearly visible) to
# the second (strength 1, strong) of each pair below.

#: membrane_compliance: share s of the commanded imprint the membrane takes, D' = D_ref - s (D_ref - D).
COMPLIANCE_DEPTH_SCALE = (0.85, 0.4)
#: elastic_spread: Gaussian sigma of the elastic smoothing, px, below the default 5 px...
SPREAD_NARROW_SIGMA_PX = (3.5, 2.0)
#: ... or above it (the side is drawn with even odds).
SPREAD_WIDE_SIGMA_PX = (7.0, 11.0)
#: coating_gloss: added specular coefficient k_s of every LED, -. The guided light is
#: grazing, so its mirror direction rarely meets the camera: less gloss than k_s + 0.5 at
#: alpha 20 changes a contact by less than 0.01.
GLOSS_DELTA_K_S = (0.5, 0.9)
#: coating_gloss: Phong shininess alpha of the glossier paint, - (the spec has 100).
GLOSS_SHININESS = (20.0, 8.0)
#: led_spectrum: magnitude of each LED's emission peak shift, nm (sign drawn per LED).
SPECTRUM_SHIFT_NM = (5.0, 25.0)
#: led_spectrum: bound of |intensity factor - 1| per LED, - (factor drawn uniformly).
SPECTRUM_INTENSITY_SPREAD = (0.05, 0.2)
#: path_attenuation: absorption coefficient mu of the elastomer, 1/m.
ATTENUATION_PER_M = (15.0, 70.0)
#: core_light_leak: gain a of the point-source irradiance at the reference distance, -
#: (0.12 is the weakest that changes a 2 mm contact by 0.01 on average).
LEAK_GAIN = (0.12, 0.4)
#: core_light_leak: reference distance r0 of the inverse-square law, m.
LEAK_REFERENCE_DISTANCE_M = 0.010
#: contact_shadow: elevation beta of the guided light above the tangent plane, degrees
#: (lower light casts longer shadows on the GelTip's straight cylinder, so strong is low).
SHADOW_ELEVATION_DEG = (10.0, 3.0)
#: contact_shadow: share of the shadowed light that is lost, -.
SHADOW_DARKNESS = (0.6, 1.0)
#: contact_shadow: farthest a shadow is looked for from the deformed region, m. A bump of
#: height h shadows at most h / tan(beta) of a flat membrane (the GelTip's cylinder along
#: its axis); the concave tip ends shadows within a chord 2 R sin(beta). This only caps
#: the search at the sensor's length.
SHADOW_MAX_REACH_M = 0.06
#: contact_shadow: a layer dimmer than one 8-bit level (linear RGB) is not traced: too little light to lose.
SHADOW_MIN_LIGHT = 1.0 / 255
#: misalignment: shift of the real frame against the simulated one, px (direction drawn).
MISALIGN_SHIFT_PX = (1.0, 6.0)
#: misalignment: rotation about the image centre, degrees (sign drawn).
MISALIGN_ROTATION_DEG = (0.2, 2.0)
#: lens_distortion: |k1| of the Brown-Conrady radial model (sign drawn).
DISTORTION_K1 = (0.05, 0.25)
#: lens_distortion: k2 = k1 * U(-this, this).
DISTORTION_K2_RATIO = 0.3
#: vignetting: focal length of the cos^n law, in camera focal lengths.
VIGNETTE_FOCAL_SCALE = (1.6, 0.9)
#: vignetting: exponent n, drawn uniformly (4 for the natural cos^4 law).
VIGNETTE_EXPONENT = (3.0, 4.0)
#: vignetting: largest offset of the optical centre from the principal point, px.
VIGNETTE_CENTRE_OFFSET_PX = 15.0
#: blur_noise: Gaussian blur sigma of the optics, px.
BLUR_SIGMA_PX = (0.8, 2.5)
#: blur_noise: read-noise standard deviation sqrt(b), image units (a webcam's read noise
#: is one to three 8-bit levels).
NOISE_READ_STD = (0.005, 0.01)
#: blur_noise: shot-noise factor a of the variance a I + b, image units.
NOISE_SHOT_FACTOR = (0.001, 0.003)
#: camera_response: encoding gamma below 1 (weak, strong)...
GAMMA_LOW = (0.9, 0.75)
#: ... or above 1 (the side is drawn with even odds).
GAMMA_HIGH = (1.15, 1.5)
#: camera_response: bound of the red and blue white-balance gains g, 1/g..g (green is 1).
WHITE_BALANCE_MAX_GAIN = (1.08, 1.25)
#: camera_response: colour cross-talk, each off-diagonal drawn in [low, this] (rows sum to 1).
CROSSTALK = (0.02, 0.1)

_CHANNELS = ("r", "g", "b")


def _lerp(pair: tuple[float, float], strength: float) -> float:
    return float(pair[0] + (pair[1] - pair[0]) * strength)


# --- what is injected --------------------------------------------------------------------


def _check_effect(effect) -> str:
    if effect not in EFFECTS:
        raise ValueError(f"effect must be one of {EFFECTS}, got {effect!r}")
    return effect


def _check_strength(strength) -> float:
    if isinstance(strength, bool) or not isinstance(strength, numbers.Real):
        raise ValueError(f"strength must be a float in [0, 1], got {strength!r}")  # noqa: TRY004 - house style
    if not (math.isfinite(strength) and 0.0 <= strength <= 1.0):
        raise ValueError(f"strength must be in [0, 1], got {strength!r}")
    return float(strength)


@dataclass(frozen=True)
class Injection:
    """One injected effect.

    effect : one of ``EFFECTS``.
    strength : in [0, 1], as drawn (0 weak but clearly visible, 1 strong).
    params : the physical parameters it maps to, by name; units in the name (``_px``,
        ``_nm``) or SI (metres, radians, 1/m). See ``sample_params``.
    """

    effect: str
    strength: float
    params: dict[str, float]

    def __post_init__(self):
        _check_effect(self.effect)
        _check_strength(self.strength)
        if not isinstance(self.params, dict):
            raise ValueError(f"params must be a dict of floats, got {type(self.params).__name__}")  # noqa: TRY004
        for key, value in self.params.items():
            if not isinstance(value, numbers.Real) or isinstance(value, bool) or not math.isfinite(value):
                raise ValueError(f"params[{key!r}] must be a finite float, got {value!r}")


def _random_sign(rng: np.random.Generator) -> float:
    return 1.0 if rng.random() < 0.5 else -1.0


def sample_params(effect: str, strength: float, rng: np.random.Generator, spec: SensorSpec,
                  camera: Camera) -> dict[str, float]:
    """Physical parameters of an effect at a strength; signs and directions from ``rng``.

    Parameters (by effect):

    * membrane_compliance: ``depth_scale`` s, -.
    * elastic_spread: ``sigma_px``, ``radius_px`` (kernel half-width, scaled with sigma).
    * coating_gloss: ``delta_k_s`` (added to every LED's k_s), ``shininess`` alpha.
    * led_spectrum: ``peak_shift_nm_<led>``, ``intensity_<led>`` per LED name.
    * path_attenuation: ``mu``, 1/m.
    * core_light_leak: ``gain`` a, ``reference_distance`` r0, m.
    * contact_shadow: ``elevation``, rad; ``darkness``, -.
    * misalignment: ``shift_x_px``, ``shift_y_px``, ``rotation`` (rad, counter-clockwise as
      displayed).
    * lens_distortion: ``k1``, ``k2``.
    * vignetting: ``exponent`` n, ``focal_px`` f_v, ``centre_dx_px``, ``centre_dy_px``
      (optical centre minus principal point).
    * blur_noise: ``blur_sigma_px``, ``noise_a``, ``noise_b`` (variance a I + b).
    * camera_response: ``gamma_enc``, ``gain_r``, ``gain_g``, ``gain_b``,
      ``crosstalk_<row><col>`` for the off-diagonal cross-talk (rows r, g, b).
    """
    _check_effect(effect)
    s = _check_strength(strength)
    if effect == "membrane_compliance":
        return {"depth_scale": _lerp(COMPLIANCE_DEPTH_SCALE, s)}
    if effect == "elastic_spread":
        sigma = _lerp(SPREAD_WIDE_SIGMA_PX if rng.random() < 0.5 else SPREAD_NARROW_SIGMA_PX, s)
        return {"sigma_px": sigma, "radius_px": float(_kernel_radius(spec.elastic, sigma))}
    if effect == "coating_gloss":
        return {"delta_k_s": _lerp(GLOSS_DELTA_K_S, s), "shininess": _lerp(GLOSS_SHININESS, s)}
    if effect == "led_spectrum":
        params = {}
        for led in spec.leds:
            params[f"peak_shift_nm_{led.name}"] = _random_sign(rng) * _lerp(SPECTRUM_SHIFT_NM, s)
            params[f"intensity_{led.name}"] = 1.0 + float(rng.uniform(-1, 1)) * _lerp(SPECTRUM_INTENSITY_SPREAD, s)
        return params
    if effect == "path_attenuation":
        return {"mu": _lerp(ATTENUATION_PER_M, s)}
    if effect == "core_light_leak":
        return {"gain": _lerp(LEAK_GAIN, s), "reference_distance": LEAK_REFERENCE_DISTANCE_M}
    if effect == "contact_shadow":
        return {"elevation": math.radians(_lerp(SHADOW_ELEVATION_DEG, s)), "darkness": _lerp(SHADOW_DARKNESS, s)}
    if effect == "misalignment":
        shift, direction = _lerp(MISALIGN_SHIFT_PX, s), float(rng.uniform(0, 2 * math.pi))
        return {"shift_x_px": shift * math.cos(direction), "shift_y_px": shift * math.sin(direction),
                "rotation": _random_sign(rng) * math.radians(_lerp(MISALIGN_ROTATION_DEG, s))}
    if effect == "lens_distortion":
        k1 = _random_sign(rng) * _lerp(DISTORTION_K1, s)
        return {"k1": k1, "k2": k1 * float(rng.uniform(-DISTORTION_K2_RATIO, DISTORTION_K2_RATIO))}
    if effect == "vignetting":
        offset, direction = VIGNETTE_CENTRE_OFFSET_PX * math.sqrt(rng.random()), float(rng.uniform(0, 2 * math.pi))
        return {"exponent": float(rng.uniform(*VIGNETTE_EXPONENT)),
                "focal_px": camera.f * _lerp(VIGNETTE_FOCAL_SCALE, s),
                "centre_dx_px": offset * math.cos(direction), "centre_dy_px": offset * math.sin(direction)}
    if effect == "blur_noise":
        return {"blur_sigma_px": _lerp(BLUR_SIGMA_PX, s), "noise_a": _lerp(NOISE_SHOT_FACTOR, s),
                "noise_b": _lerp(NOISE_READ_STD, s) ** 2}
    # camera_response
    params = {"gamma_enc": _lerp(GAMMA_HIGH if rng.random() < 0.5 else GAMMA_LOW, s)}
    log_bound = math.log(_lerp(WHITE_BALANCE_MAX_GAIN, s))
    for c in _CHANNELS:
        params[f"gain_{c}"] = 1.0 if c == "g" else math.exp(float(rng.uniform(-log_bound, log_bound)))
    for i, row in enumerate(_CHANNELS):
        for j, col in enumerate(_CHANNELS):
            if i != j:
                params[f"crosstalk_{row}{col}"] = float(rng.uniform(CROSSTALK[0], _lerp(CROSSTALK, s)))
    return params


def _param(injection: Injection, key: str) -> float:
    if key not in injection.params:
        raise ValueError(f"{injection.effect} injection needs params[{key!r}], got keys {sorted(injection.params)}")
    return float(injection.params[key])


# --- membrane ----------------------------------------------------------------------------


def comply(depth: np.ndarray, ref_depth: np.ndarray, depth_scale: float) -> np.ndarray:
    """A compliant membrane and sensor take only part of the commanded imprint.

    D' = D_ref - s (D_ref - D).  depth, ref_depth : (H, W) float, metres, planar z-depth;
    depth_scale : s in (0, 1], 1 the rigid simulator.  Returns (H, W), depth's dtype.
    """
    if not 0.0 < depth_scale <= 1.0:
        raise ValueError(f"depth_scale must be in (0, 1], got {depth_scale}")
    return (ref_depth - depth.dtype.type(depth_scale) * (ref_depth - depth)).astype(depth.dtype, copy=False)


def _kernel_radius(elastic: Elastic, sigma_px: float) -> int:
    """The default kernel's half-width in sigmas, kept for another sigma, px."""
    return max(1, round(elastic.radius_px * sigma_px / elastic.sigma_px))


def spread_elastic(elastic: Elastic, sigma_px: float, radius_px: int | None = None) -> Elastic:
    """The elastic model with another smoothing width (sigma, px; radius scaled with it)."""
    if not sigma_px > 0:
        raise ValueError(f"sigma_px must be > 0, got {sigma_px}")
    radius = _kernel_radius(elastic, sigma_px) if radius_px is None else int(radius_px)
    return Elastic(sigma_px=float(sigma_px), radius_px=radius)


# --- the facade --------------------------------------------------------------------------


class Injector:
    """Fast-path renders of contacts with injected effects, for one sensor and renderer setting.

    Parameters
    ----------
    spec : the sensor.
    field : light-field method, one of ``phong_reference.bake.METHODS`` (baked, cached on disk).
    background : "none", "solid", a no-contact image path, or an (H, W, 3) float array in
        [0, 1]; the same meaning as ``phong_reference.background.make_background``.
    rectify : as ``phong_reference.render.light_vectors``.
    ref_depth : (H, W) float, metres, the no-contact depth D_ref the datasets use; default
        the ray-cast one of the membrane mesh (``scenes.camera.reference_depth``).

    With no injections ``render`` gives exactly the ``PhongDatasetRenderer`` image of the
    same settings.
    """

    def __init__(self, spec: SensorSpec, field: str = "plane", background="none", rectify: bool = False,
                 *, ref_depth: np.ndarray | None = None):
        if field not in METHODS:
            raise ValueError(f"field must be one of {METHODS}, got {field!r}")
        self.spec = spec
        self.camera = Camera.from_spec(spec)
        self.mesh = membrane_mesh(spec)
        fields = bake(self.mesh, self.camera, spec.leds, field)
        ref = fields.depth if ref_depth is None else ref_depth
        self.ref_depth = check_depth(ref, self.camera, "ref_depth").astype(np.float32)  # (H, W) metres, D_ref
        if isinstance(background, (str, Path)):
            self.background = make_background(background, self.camera)
        else:
            self.background = check_background(background, self.camera)  # (H, W, 3) linear RGB
        self.L = light_vectors(fields, rectify)  # (M, 3, H, W) float32, L_m = -field
        self._renderer = Renderer(spec, self.camera, self.ref_depth, self.L, self.background)
        self._B = np.ascontiguousarray(self.background.transpose(2, 0, 1))  # (3, H, W)
        self._P_ref = back_project(self.ref_depth, self.camera, channels_first=True)  # (3, H, W) metres
        self._inward = -np.asarray(fields.normals, dtype=np.float64).transpose(2, 0, 1)  # (3, H, W) undeformed
        self._geodesic: np.ndarray | None = None  # (M, H, W) float32 metres, from each LED, on first use

    @property
    def no_contact(self) -> np.ndarray:
        """(H, W, 3) float32: the plain no-contact image."""
        return self._renderer.base

    def sample(self, effect: str, rng: np.random.Generator, strength: float | None = None) -> Injection:
        """Draw an injection: ``strength`` uniformly in [0, 1] when None, then its parameters."""
        _check_effect(effect)
        if not isinstance(rng, np.random.Generator):
            raise ValueError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")  # noqa: TRY004
        strength = float(rng.uniform(0.0, 1.0)) if strength is None else _check_strength(strength)
        return Injection(effect, strength, sample_params(effect, strength, rng, self.spec, self.camera))

    def render(self, depth: np.ndarray, injections=(), rng: np.random.Generator | None = None) -> np.ndarray:
        """The fast-path image of a contact with the injected effects, in physical order.

        depth : (H, W) float, metres, planar z-depth.  injections : Injections of distinct
        effects (or one Injection).  rng : only for the noise of ``blur_noise`` (required
        then).  Returns (H, W, 3) float32 linear RGB in [0, 1].
        """
        depth = check_depth(depth, self.camera)
        chosen = self._check_injections(injections)
        if "blur_noise" in chosen and not isinstance(rng, np.random.Generator):
            raise ValueError(f"rng must be a numpy.random.Generator for blur_noise's sensor noise, got {rng!r}")
        depth = np.asarray(depth, dtype=np.float32)
        # As PhongDatasetRenderer: depth within rasterisation noise of D_ref is no contact.
        depth = np.where(np.abs(depth - self.ref_depth) <= CONTACT_EPS_M, self.ref_depth, depth)
        if chosen.keys() & SHADED_EFFECTS:
            image = self._shade(depth, chosen)
        else:
            image = self._renderer.render(depth)
        if not chosen:
            return image
        image = self._optics(image, chosen)
        image = self._sensor(image, chosen, rng)
        return np.clip(image, 0.0, 1.0).astype(np.float32, copy=False)

    def _check_injections(self, injections) -> dict[str, Injection]:
        if injections is None:
            injections = ()
        if isinstance(injections, Injection):
            injections = (injections,)
        chosen: dict[str, Injection] = {}
        for inj in injections:
            if not isinstance(inj, Injection):
                raise ValueError(f"injections must hold Injection objects, got {type(inj).__name__}")  # noqa: TRY004
            if inj.effect in chosen:
                raise ValueError(f"injections hold {inj.effect!r} twice; expected distinct effects")
            chosen[inj.effect] = inj
        return chosen

    def _shade(self, depth: np.ndarray, chosen: dict[str, Injection]) -> np.ndarray:
        """Membrane, light transport and shading, then background, clip and mask: (H, W, 3)."""
        ref = self.ref_depth
        if "membrane_compliance" in chosen:
            depth = comply(depth, ref, _param(chosen["membrane_compliance"], "depth_scale"))
        elastic = self.spec.elastic
        if "elastic_spread" in chosen:
            inj = chosen["elastic_spread"]
            elastic = spread_elastic(elastic, _param(inj, "sigma_px"), round(_param(inj, "radius_px")))
        leds, material = self.spec.leds, self.spec.material
        if "coating_gloss" in chosen:
            inj = chosen["coating_gloss"]
            leds, material = gloss(leds, material, _param(inj, "delta_k_s"), _param(inj, "shininess"))
        if "led_spectrum" in chosen:
            inj = chosen["led_spectrum"]
            leds = shift_spectra(leds, [_param(inj, f"peak_shift_nm_{led.name}") for led in leds],
                                 [_param(inj, f"intensity_{led.name}") for led in leds])
        d_def = deform(depth, ref, elastic)
        P = back_project(d_def, self.camera, channels_first=True)  # (3, H, W) metres
        N, _ = normals(P)  # (3, H, W), facing the camera: inward
        layers = led_layers(P, N, self.L, leds, material)  # (M, 3, H, W) I_m
        if "path_attenuation" in chosen:
            layers *= transmittance(self._geodesic_maps(), _param(chosen["path_attenuation"], "mu"))[:, None]
        ambient = material.ambient * self._B  # (3, H, W), k_a i_a B
        if "contact_shadow" in chosen:
            ambient = ambient.copy()
            self._cast_shadows(d_def, P, leds, layers, ambient, chosen["contact_shadow"])
        I = ambient + layers.sum(axis=0)
        if "core_light_leak" in chosen:
            inj = chosen["core_light_leak"]
            I += core_leak(P, N, leds, _param(inj, "gain"), _param(inj, "reference_distance"))
        return finish(I, self.camera.mask)

    def _cast_shadows(self, d_def, P, leds, layers, ambient, inj: Injection) -> None:
        """Darken, in place, each LED's layer and the ambient term where the imprint's rim
        occludes the guided light. The ambient term k_a i_a B stands for the no-contact
        guided light of all LEDs, so it keeps the LEDs' mean share, weighted by k_d colour."""
        moved = d_def < self.ref_depth - CONTACT_EPS_M  # the membrane moved
        occluder = deformed_grid(P, moved)
        if occluder is None:
            return
        elevation = _param(inj, "elevation")
        # Receivers: pixels whose undeformed point is within a shadow's reach of the
        # occluder, the longest a bump of its height casts on a flat membrane, capped.
        P_ref = self._P_ref
        height = float(np.sqrt(((P[:, moved] - P_ref[:, moved]) ** 2).sum(axis=0)).max())
        reach = min(height / math.tan(elevation * min(SHADOW_SOFT_ELEVATIONS)), SHADOW_MAX_REACH_M)
        centre = occluder.bounds.mean(axis=0)
        radius = 0.5 * float(np.linalg.norm(np.ptp(occluder.bounds, axis=0)))
        near = ((P_ref - centre[:, None, None]) ** 2).sum(axis=0) < (radius + reach) ** 2
        lit = layers.max(axis=1) > SHADOW_MIN_LIGHT  # (M, H, W): light to lose
        lit |= (ambient > 0).any(axis=0)
        rows, cols = np.nonzero(near & self.camera.mask & lit.any(axis=0))
        lit = lit[:, rows, cols]  # (M, K)
        light = self.L[:, :, rows, cols].transpose(0, 2, 1)  # (M, K, 3)
        vis = shadow_visibility(P[:, rows, cols].T, light, self._inward[:, rows, cols].T, occluder, self.mesh,
                                elevation, where=lit)
        kept = (1.0 - _param(inj, "darkness") * (1.0 - vis)).astype(layers.dtype)  # (M, K)
        layers[:, :, rows, cols] *= kept[:, None]
        weight = np.array([led.k_d * np.asarray(led.colour) for led in leds], dtype=layers.dtype)  # (M, 3)
        ambient[:, rows, cols] *= (weight.T @ kept) / np.maximum(weight.sum(axis=0), 1e-12)[:, None]

    def _geodesic_maps(self) -> np.ndarray:
        """(M, H, W) float32 metres: exact geodesic distance over the membrane from the mesh
        vertex nearest each LED, at each pixel's undeformed surface point (cached)."""
        if self._geodesic is None:
            # pygeodesic's exact MMP algorithm, through the one module allowed to import it.
            from phong_reference.geodesic import GeodesicBaker

            baker = GeodesicBaker(self.mesh)
            samples = cast_rays(self.mesh, self.camera, whole_frame=True)
            maps = []
            for vertex in snap_leds(self.mesh, self.spec.leds).vertices:
                d = baker.distance(int(vertex))  # (N,) metres
                reached = np.isfinite(d)
                d = np.where(reached, d, d[reached].max())  # unreachable: as far as the farthest
                at = samples.interpolate(self.mesh, d)
                maps.append(samples.scatter(at.astype(np.float32), fill=float(at.max())))
            self._geodesic = np.stack(maps)
        return self._geodesic

    def _optics(self, image: np.ndarray, chosen: dict[str, Injection]) -> np.ndarray:
        cam = self.camera
        if "misalignment" in chosen:
            inj = chosen["misalignment"]
            image = misalign(image, _param(inj, "shift_x_px"), _param(inj, "shift_y_px"), _param(inj, "rotation"),
                             (cam.cx, cam.cy))
        if "lens_distortion" in chosen:
            inj = chosen["lens_distortion"]
            image = distort(image, cam, _param(inj, "k1"), _param(inj, "k2"))
        if "vignetting" in chosen:
            inj = chosen["vignetting"]
            centre = (cam.cx + _param(inj, "centre_dx_px"), cam.cy + _param(inj, "centre_dy_px"))
            image = vignette(image, centre, _param(inj, "focal_px"), _param(inj, "exponent"))
        if "blur_noise" in chosen:
            image = blur(image, _param(chosen["blur_noise"], "blur_sigma_px"))
        return image

    def _sensor(self, image: np.ndarray, chosen: dict[str, Injection], rng: np.random.Generator | None) -> np.ndarray:
        if "camera_response" in chosen:
            inj = chosen["camera_response"]
            gains = [_param(inj, f"gain_{c}") for c in _CHANNELS]
            C = np.zeros((3, 3))
            for i, row in enumerate(_CHANNELS):
                for j, col in enumerate(_CHANNELS):
                    if i != j:
                        C[i, j] = _param(inj, f"crosstalk_{row}{col}")
                C[i, i] = 1.0 - C[i].sum()  # rows sum to 1: cross-talk moves light, keeps grey grey
            image = respond(image, _param(inj, "gamma_enc"), gains, C)
        if "blur_noise" in chosen:
            inj = chosen["blur_noise"]
            image = add_noise(image, _param(inj, "noise_a"), _param(inj, "noise_b"), rng)
        return image
