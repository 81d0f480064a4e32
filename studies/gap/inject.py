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

import dataclasses
import math
import numbers
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import trimesh

from pbr_tactile.spectra import film_response, gaussian
from phong_reference.background import check_background, make_background
from phong_reference.bake import METHODS, bake
from phong_reference.normals import normals
from phong_reference.phong import shade
from phong_reference.render import Renderer, finish, light_vectors
from phong_reference.sources import snap_leds
from scenes.camera import CONTACT_EPS_M, Camera, back_project, cast_rays, check_depth
from scenes.elastic import deform
from scenes.geometry import membrane_mesh
from scenes.spec import LED, Elastic, Material, SensorSpec

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
#: Out-of-band transmission of a Bayer colour filter, as a share of the LED's strongest
#: channel: without it the ratio R_c(peak + delta) / R_c(peak) of a channel deep in the
#: Gaussian tail (the blue response to a red LED) reaches 50.
FILTER_FLOOR = 0.02
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
#: contact_shadow: the light is an extended source: elevations beta times these, averaged.
SHADOW_SOFT_ELEVATIONS = (0.7, 0.9, 1.1, 1.3)
#: contact_shadow: farthest a shadow is looked for from the deformed region, m. A bump of
#: height h shadows at most h / tan(beta) of a flat membrane (the GelTip's cylinder along
#: its axis); the concave tip ends shadows within a chord 2 R sin(beta). This only caps
#: the search at the sensor's length.
SHADOW_MAX_REACH_M = 0.06
#: contact_shadow: a layer dimmer than one 8-bit level (linear RGB) is not traced: too little light to lose.
SHADOW_MIN_LIGHT = 1.0 / 255
#: contact_shadow: shadow rays start this far along their direction, m (Embree is float32).
SHADOW_RAY_OFFSET_M = 1e-5
#: contact_shadow: an occluder must come this much closer than the undeformed membrane, m.
SHADOW_TOLERANCE_M = 5e-5
#: misalignment: shift of the real frame against the simulated one, px (direction drawn).
MISALIGN_SHIFT_PX = (1.0, 6.0)
#: misalignment: rotation about the image centre, degrees (sign drawn).
MISALIGN_ROTATION_DEG = (0.2, 2.0)
#: lens_distortion: |k1| of the Brown-Conrady radial model (sign drawn).
DISTORTION_K1 = (0.05, 0.25)
#: lens_distortion: k2 = k1 * U(-this, this).
DISTORTION_K2_RATIO = 0.3
#: lens_distortion: largest undistorted radius tabulated, in focal lengths.
DISTORTION_MAX_RADIUS = 3.0
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


# --- shading -----------------------------------------------------------------------------


def gloss(leds: tuple[LED, ...], material: Material, delta_k_s: float,
          shininess: float) -> tuple[tuple[LED, ...], Material]:
    """A glossier coating: every LED's k_s raised by ``delta_k_s``, Phong alpha set to ``shininess``."""
    if not shininess > 0:
        raise ValueError(f"shininess must be > 0, got {shininess}")
    leds = tuple(dataclasses.replace(led, k_s=led.k_s + float(delta_k_s)) for led in leds)
    return leds, dataclasses.replace(material, shininess=float(shininess))


def spectral_ratio(peak_nm: float, fwhm_nm: float, shift_nm: float) -> np.ndarray:
    """(3,) camera RGB response to an LED whose peak moved by ``shift_nm``, over the original.

    R_c = film_response(gaussian(peak, fwhm)) through the camera's bands, plus an
    out-of-band floor of ``FILTER_FLOOR`` times the original's strongest channel.
    """
    before = film_response(gaussian(peak_nm, fwhm_nm))
    after = film_response(gaussian(peak_nm + shift_nm, fwhm_nm))
    floor = FILTER_FLOOR * before.max()
    return (after + floor) / (before + floor)


def shift_spectra(leds: tuple[LED, ...], shifts_nm, intensities) -> tuple[LED, ...]:
    """LEDs whose emission peaks moved: colour_m * R(peak + delta_m) / R(peak) * intensity_m.

    shifts_nm, intensities : (M,) per LED, nm and -.  An LED without ``peak_nm`` and
    ``fwhm_nm`` in the spec keeps its colour (only the intensity factor applies).
    """
    out = []
    for led, shift, gain in zip(leds, shifts_nm, intensities, strict=True):
        ratio = np.ones(3)
        if led.peak_nm is not None and led.fwhm_nm is not None:
            ratio = spectral_ratio(led.peak_nm, led.fwhm_nm, float(shift))
        colour = tuple(float(c) for c in np.asarray(led.colour) * ratio * float(gain))
        peak = None if led.peak_nm is None else led.peak_nm + float(shift)
        out.append(dataclasses.replace(led, colour=colour, peak_nm=peak))
    return tuple(out)


def led_layers(P: np.ndarray, N: np.ndarray, L: np.ndarray, leds: tuple[LED, ...], material: Material) -> np.ndarray:
    """Each LED's own Phong term I_m, without the ambient background.

    P, N : (3, H, W) points (metres) and camera-facing unit normals; L : (M, 3, H, W) unit
    light vectors.  Returns (M, 3, H, W), P's dtype, linear RGB, not clipped.
    """
    dark = dataclasses.replace(material, ambient=0.0)
    zeros = np.zeros_like(P)
    return np.stack([shade(P, N, L[m : m + 1], [led], dark, zeros) for m, led in enumerate(leds)])


def transmittance(distance: np.ndarray, mu: float) -> np.ndarray:
    """Beer-Lambert: exp(-mu d), distance d in metres, mu in 1/m; same shape."""
    if not mu >= 0:
        raise ValueError(f"mu must be >= 0 1/m, got {mu}")
    return np.exp(-mu * distance)


def core_leak(P: np.ndarray, N: np.ndarray, leds: tuple[LED, ...], gain: float,
              reference_distance: float) -> np.ndarray:
    """Irradiance of LED light that crosses the glass core and meets the membrane from inside.

    Each LED is a point source at its position p_m:
    E = a colour_m max(N . w_m, 0) (r0 / |p_m - P|)^2, with w_m = (p_m - P) / |p_m - P|.

    P : (3, H, W) float, metres, surface points; N : (3, H, W) unit normals facing the
    camera, which sits inside the membrane, so they are the inward normals.
    Returns (3, H, W), P's dtype, linear RGB.
    """
    out = np.zeros_like(P)
    for led in leds:
        to_led = np.asarray(led.position, dtype=P.dtype)[:, None, None] - P  # (3, H, W), metres
        dist2 = (to_led * to_led).sum(axis=0)
        cos = np.maximum((N * to_led).sum(axis=0) / np.sqrt(dist2), 0)
        E = gain * cos * (reference_distance * reference_distance / dist2)
        out += np.asarray(led.colour, dtype=P.dtype)[:, None, None] * E
    return out


def _grid_faces(h: int, w: int) -> np.ndarray:
    """(2 (h - 1)(w - 1), 3) int triangles of an h x w vertex grid, row-major."""
    a = (np.arange(h - 1)[:, None] * w + np.arange(w - 1)[None, :]).ravel()
    return trimesh.geometry.triangulate_quads(np.stack([a, a + 1, a + w + 1, a + w], axis=1))


def deformed_grid(points: np.ndarray, moved: np.ndarray) -> trimesh.Trimesh | None:
    """The deformed part of the surface as a triangle grid: the pixel points P (3, H, W),
    metres, over the bounding box of ``moved`` (H, W) bool grown by one pixel; None if
    nothing moved."""
    box = _box(moved, 1)
    if box is None:
        return None
    grid = np.asarray(points[(slice(None),) + box], dtype=np.float64)
    h, w = grid.shape[1:]
    if h < 2 or w < 2:
        return None
    return trimesh.Trimesh(grid.reshape(3, -1).T, _grid_faces(h, w), process=False)


def shadow_visibility(
    points: np.ndarray,
    light: np.ndarray,
    inward: np.ndarray,
    occluder: trimesh.Trimesh,
    membrane: trimesh.Trimesh,
    elevation: float,
    where: np.ndarray | None = None,
) -> np.ndarray:
    """Share of each LED's guided light that the deformed membrane lets through.

    Light arrives along the tangent L_m (towards the LED) tilted by the elevation beta
    towards the camera side: w = cos(beta) t_m + sin(beta) n, with t_m the part of L_m
    in the undeformed tangent plane (unit) and n the undeformed inward normal. A point is
    shadowed when the ray from it along w meets the deformed surface (``occluder``)
    before it would meet the undeformed ``membrane``: on the GelTip's concave inside,
    light at elevation beta has come off the membrane a chord 2 R sin(beta) away, so only
    nearer occluders count. The source is extended: beta times each of
    ``SHADOW_SOFT_ELEVATIONS``, averaged.

    points : (K, 3) float, metres, the receiving (deformed) surface points.
    light : (M, K, 3) float, light vectors L_m there; zero where the LED's light does not reach.
    inward : (K, 3) float, unit inward normals of the undeformed membrane there.
    occluder : the deformed part of the membrane, metres (``deformed_grid``).
    membrane : the undeformed membrane mesh, metres.
    elevation : beta, rad, in (0, pi / 2).
    where : (M, K) bool, the points whose light matters (the others are not traced and
        count as lit); default all.

    Returns (M, K) float64 in [0, 1], 1 fully lit.
    """
    if not 0 < elevation < math.pi / 2:
        raise ValueError(f"elevation must be in (0, pi/2) rad, got {elevation}")
    points = np.asarray(points, dtype=np.float64)
    n = np.asarray(inward, dtype=np.float64)
    centre = occluder.bounds.mean(axis=0)  # bounding sphere of the occluder, for culling
    radius = 0.5 * float(np.linalg.norm(np.ptp(occluder.bounds, axis=0))) + SHADOW_RAY_OFFSET_M
    visible = np.ones(light.shape[:2])
    for m in range(len(light)):
        idx = np.arange(len(points)) if where is None else np.flatnonzero(where[m])
        L_m = np.asarray(light[m, idx], dtype=np.float64)
        t = L_m - (L_m * n[idx]).sum(axis=1, keepdims=True) * n[idx]
        norm = np.linalg.norm(t, axis=1)
        # No tangent light, or an occluder behind the point (away from the light): lit.
        keep = (norm > 1e-6) & (((centre - points[idx]) * t).sum(axis=1) > -radius * norm)
        idx, t = idx[keep], t[keep] / norm[keep, None]
        # Every ray of the point lies in the plane through it spanned by t and n: an
        # occluder off that plane is missed at any elevation.
        side = np.cross(t, n[idx])
        keep = np.abs(((centre - points[idx]) * side).sum(axis=1)) < radius
        idx, t = idx[keep], t[keep]
        if idx.size == 0:
            continue
        share = np.zeros(idx.size)
        for factor in SHADOW_SOFT_ELEVATIONS:
            beta = min(elevation * factor, math.pi / 2 - 1e-3)
            dirs = math.cos(beta) * t + math.sin(beta) * n[idx]
            origins = points[idx] + SHADOW_RAY_OFFSET_M * dirs
            # Only rays whose line passes the occluder's bounding sphere, ahead, can hit it.
            to_c = centre - origins
            along = (to_c * dirs).sum(axis=1)
            near = (along > -radius) & ((to_c * to_c).sum(axis=1) - along**2 < radius**2)
            hit = np.zeros(idx.size, dtype=bool)
            if near.any():
                hit[near] = _occluded(occluder, membrane, origins[near], dirs[near])
            share += ~hit
        visible[m, idx] = share / len(SHADOW_SOFT_ELEVATIONS)
    return visible


def _first_hit(mesh: trimesh.Trimesh, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """(K,) distance to each ray's first hit, metres; inf where it misses."""
    _, ray, loc = mesh.ray.intersects_id(origins, dirs, multiple_hits=False, return_locations=True)
    t = np.full(len(origins), np.inf)
    t[ray] = np.einsum("ij,ij->i", np.asarray(loc) - origins[ray], dirs[ray])
    return t


def _occluded(surface: trimesh.Trimesh, membrane: trimesh.Trimesh, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    hit = _first_hit(surface, origins, dirs)
    occluded = np.isfinite(hit)
    if occluded.any():
        idx = np.flatnonzero(occluded)
        occluded[idx] = hit[idx] < _first_hit(membrane, origins[idx], dirs[idx]) - SHADOW_TOLERANCE_M
    return occluded


# --- optics ------------------------------------------------------------------------------


def misalign(image: np.ndarray, shift_x_px: float, shift_y_px: float, rotation: float,
             centre: tuple[float, float]) -> np.ndarray:
    """The frame rotated by ``rotation`` rad (counter-clockwise as displayed) about ``centre``
    (u, v) px, then shifted by (shift_x_px, shift_y_px) px; black where nothing maps.

    image : (H, W, 3) float32.  Returns the same shape and dtype.
    """
    A = cv2.getRotationMatrix2D((float(centre[0]), float(centre[1])), math.degrees(rotation), 1.0)
    A[:, 2] += (shift_x_px, shift_y_px)
    h, w = image.shape[:2]
    return cv2.warpAffine(image, A, (w, h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def distortion_maps(camera: Camera, k1: float, k2: float) -> tuple[np.ndarray, np.ndarray]:
    """Where each pixel of the distorted image looks in the ideal (pinhole) one.

    A Brown-Conrady lens moves the ideal point at normalised radius r (about the
    principal point, in focal lengths) to r (1 + k1 r^2 + k2 r^4). cv2.projectPoints
    tabulates that along the monotone branch, and the table is inverted per pixel;
    pixels whose radius no ideal point reaches get -1 (black through cv2.remap).

    Returns map_x, map_y : (H, W) float32, px.
    """
    r = np.linspace(0.0, DISTORTION_MAX_RADIUS, 4096)
    K = np.array([[camera.f, 0, camera.cx], [0, camera.f, camera.cy], [0, 0, 1.0]])
    table, _ = cv2.projectPoints(np.stack([r, np.zeros_like(r), np.ones_like(r)], 1), np.zeros(3), np.zeros(3), K,
                                 np.array([k1, k2, 0.0, 0.0]))
    r_d = (table[:, 0, 0] - camera.cx) / camera.f
    rising = np.diff(r_d) > 0
    end = len(r) if rising.all() else int(np.argmin(rising)) + 1  # the fold, if any
    r, r_d = r[:end], r_d[:end]
    v, u = np.mgrid[0 : camera.height, 0 : camera.width].astype(np.float64)
    du, dv = (u - camera.cx) / camera.f, (v - camera.cy) / camera.f
    rho = np.hypot(du, dv)  # distorted radius of each pixel, focal lengths
    ideal = np.interp(rho, r_d, r, right=np.nan)
    scale = np.divide(ideal, rho, out=np.ones_like(rho), where=rho > 0)
    map_x = np.where(np.isfinite(ideal), camera.cx + camera.f * du * scale, -1.0).astype(np.float32)
    map_y = np.where(np.isfinite(ideal), camera.cy + camera.f * dv * scale, -1.0).astype(np.float32)
    return map_x, map_y


def distort(image: np.ndarray, camera: Camera, k1: float, k2: float) -> np.ndarray:
    """The image through a Brown-Conrady lens (k1, k2 radial); (H, W, 3) float32 in and out."""
    map_x, map_y = distortion_maps(camera, k1, k2)
    return cv2.remap(image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def vignette(image: np.ndarray, centre: tuple[float, float], focal_px: float, exponent: float) -> np.ndarray:
    """Off-axis falloff V = cos(theta)^n, tan(theta) = r / f_v, r the distance to ``centre``.

    image : (H, W, 3) float; centre : (u, v) px, the optical centre; focal_px : f_v, px;
    exponent : n (4 for the natural cos^4 law, 0 for none).  Returns image * V, same dtype.
    """
    if not focal_px > 0:
        raise ValueError(f"focal_px must be > 0, got {focal_px}")
    h, w = image.shape[:2]
    v, u = np.mgrid[0:h, 0:w]
    theta = np.arctan(np.hypot(u - centre[0], v - centre[1]) / focal_px)
    return image * (np.cos(theta) ** exponent).astype(image.dtype)[..., None]


def blur(image: np.ndarray, sigma_px: float) -> np.ndarray:
    """The optics' point spread as a Gaussian of ``sigma_px`` px; same shape and dtype."""
    if not sigma_px > 0:
        raise ValueError(f"sigma_px must be > 0, got {sigma_px}")
    return cv2.GaussianBlur(image, (0, 0), sigma_px)


# --- sensor ------------------------------------------------------------------------------


def respond(image: np.ndarray, gamma_enc: float, gains, crosstalk: np.ndarray) -> np.ndarray:
    """The camera's own response: out = clip(gains * (C @ in), 0, 1) ** (1 / gamma_enc).

    image : (H, W, 3) float in [0, 1]; gains : (3,) white balance; crosstalk : C (3, 3),
    rows summing to 1 (C[i, j] is how much of channel j leaks into channel i).
    Returns the same shape, image's dtype.
    """
    if not gamma_enc > 0:
        raise ValueError(f"gamma_enc must be > 0, got {gamma_enc}")
    mixed = image @ np.asarray(crosstalk, dtype=image.dtype).T * np.asarray(gains, dtype=image.dtype)
    return np.clip(mixed, 0, 1) ** image.dtype.type(1.0 / gamma_enc)


def add_noise(image: np.ndarray, a: float, b: float, rng: np.random.Generator) -> np.ndarray:
    """Signal-dependent Gaussian sensor noise of variance a I + b; same shape and dtype."""
    if not (a >= 0 and b >= 0):
        raise ValueError(f"noise a and b must be >= 0, got a={a}, b={b}")
    std = np.sqrt(a * np.maximum(image, 0) + b)
    return image + std * rng.standard_normal(image.shape, dtype=np.float32).astype(image.dtype, copy=False)


# --- the facade --------------------------------------------------------------------------


def _box(changed: np.ndarray, margin: int) -> tuple[slice, slice] | None:
    """Slices of the bounding box of ``changed`` (H, W) bool grown by ``margin`` px; None if empty."""
    rows = np.flatnonzero(changed.any(axis=1))
    if rows.size == 0:
        return None
    cols = np.flatnonzero(changed.any(axis=0))
    h, w = changed.shape
    return (slice(max(int(rows[0]) - margin, 0), min(int(rows[-1]) + 1 + margin, h)),
            slice(max(int(cols[0]) - margin, 0), min(int(cols[-1]) + 1 + margin, w)))


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
