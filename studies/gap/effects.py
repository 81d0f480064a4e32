"""The catalogue of candidate unmodelled effects, and each one's physical model.

Every effect is a parametric stage that can be added to the fast simulator
(``studies.gap.model.FastModel`` composes them). Its parameters have bounds, an identity
value (where the effect is absent) and units; the diagnosis fits them on training samples.
The functions here are pure array functions, in the simulator's order:

1. membrane: ``membrane_compliance`` (the imprint is shallower than commanded),
   ``elastic_spread`` (another width of the elastic smoothing);
2. light and paint, per LED m: ``path_attenuation`` (light fading by a monotone,
   piecewise-linear optical depth tau(d) of a distance the data choose: its path over
   the membrane, from each LED for I_m and from the LEDs' ring for the guided light the
   background term stands for, or its height along the sensor's axis, or a blend;
   I_m exp(-w_led tau(d_m)), k_a B exp(-w_ambient tau(d_B))), ``contact_shadow`` (the imprint,
   pushed into the sensor, hides the light arriving low along the field, from the LED's
   own term and the background it stands for; a march towards the light over the depth map),
   ``coating_gloss`` (an extra specular lobe k_g (R_m . V)^alpha_g), ``core_light_leak``
   (light crossing the glass core straight from each LED: a_m |N . w_m| / (1 + (d_m /
   lambda)^2)), ``led_spectrum`` (each LED's peak shifted and its power scaled, seen
   through the camera's spectral response);
3. optics and sensor: ``misalignment`` and ``lens_distortion`` (one resampling of the
   image; a misalignment moves the membrane's image under the lens's fixed image circle
   and background, or, at ``frame_share`` 1, the whole frame), ``vignetting`` (1 / (1 + a r^2 + b r^4)), ``blur_noise`` (Gaussian blur; the
   noise is estimated, not added, since a prediction is a mean), ``camera_response``
   (a 3x3 colour matrix, white balance and colour mixing of either sign, a black level,
   and the response curve).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

#: Effect names, in the order of the issue and of every report.
EFFECTS = ("core_light_leak", "path_attenuation", "membrane_compliance", "elastic_spread", "coating_gloss",
           "contact_shadow", "camera_response", "vignetting", "lens_distortion", "misalignment", "blur_noise",
           "led_spectrum")

#: Where in the simulator each effect acts.
STAGES = {"membrane_compliance": "membrane", "elastic_spread": "membrane", "path_attenuation": "light",
          "contact_shadow": "light", "coating_gloss": "light", "core_light_leak": "light",
          "led_spectrum": "light", "misalignment": "optics", "lens_distortion": "optics", "vignetting": "optics",
          "blur_noise": "optics", "camera_response": "sensor"}


@dataclass(frozen=True)
class Param:
    """One fitted parameter: bounds, the value at which the effect is absent, its unit."""

    name: str
    low: float
    high: float
    identity: float
    unit: str
    doc: str


@dataclass(frozen=True)
class Effect:
    name: str
    stage: str
    params: tuple[Param, ...]
    doc: str

    @property
    def identity(self) -> dict[str, float]:
        return {p.name: p.identity for p in self.params}


#: path_attenuation: the fade's optical depth is piecewise linear in the distance, over
#: this many equal stretches from 0 to the longest distance the image circle holds (a
#: continuous profile with a kink at each knot; past the last, the light fades no more).
FADE_KNOTS = 6
#: path_attenuation: bound of each stretch's optical depth (exp(-3) = 5 % of the light
#: left over one stretch).
FADE_DEPTH_MAX = 3.0

#: vignetting: the fall-off's log is piecewise linear in r = radius / f over this many
#: equal stretches from the optical centre to the image circle's farthest pixel (plus the
#: centre's largest offset); each stretch's log fall-off is at most VIGNETTE_DEPTH_MAX.
VIGNETTE_KNOTS = 6
VIGNETTE_DEPTH_MAX = 1.5
#: vignetting: bound of the optical centre's offset, full-resolution pixels.
VIGNETTE_CENTRE_PX = 40.0

#: Clipping bounds of float32 images: numpy clips a float32 array about five times faster
#: with float32 bounds than with Python floats (measured: 6 ms against 31 ms for 32
#: working images), and fits clip every image of every evaluation.
ZERO, ONE = np.float32(0.0), np.float32(1.0)

#: Colour channels, in image order.
CHANNELS = ("r", "g", "b")
#: camera_response: the colour matrix's off-diagonal entries, (output, input) channel.
MIX_ENTRIES = tuple((o, i) for o in CHANNELS for i in CHANNELS if o != i)
#: camera_response: bound of each off-diagonal, -: a strong colour correction matrix
#: (a camera's, from raw to its colour space) has off-diagonals of -0.6 to 0.3.
MIX_BOUND = 0.8
#: The capture's exposure. A camera that sets its own exposure (auto-exposure, settled on
#: the sensor's frame: ``rig.camera``, and the reference's rule for the virtual rig) scales
#: the whole image whenever an effect changes how bright the frame is: a core leak darkens
#: it, absorption or vignetting brighten its middle. Where the real dataset's camera says
#: so (``renderer.camera.exposure`` "auto"), every candidate without gains of its own is
#: fitted with it (``with_exposure``).
CAPTURE_EXPOSURE = Param("exposure", 0.25, 4.0, 1.0, "-", "the capture's own exposure gain (an auto-exposed camera's)")


def exposure_scale(params: dict) -> float:
    """The product of the capture's exposure gains (parameters named ``exposure``) in
    ``params`` ({effect: {param: value}})."""
    return math.prod(p.get("exposure", 1.0) for p in params.values())


def with_exposure(catalogue: dict[str, Effect], exposure: Param = CAPTURE_EXPOSURE,
                  names: tuple[str, ...] | None = None) -> dict[str, Effect]:
    """``catalogue`` with ``exposure`` fitted alongside every effect of ``names`` (default:
    every one with parameters but camera_response, whose colour matrix holds a gain)."""
    names = tuple(n for n, e in catalogue.items() if e.params and n != "camera_response") if names is None else names
    return {n: dataclasses.replace(e, params=e.params + (exposure,)) if n in names else e for n, e in catalogue.items()}


def catalogue(n_leds: int, sigma_px: float) -> dict[str, Effect]:
    """The effects for a sensor with ``n_leds`` LEDs whose elastic smoothing has width
    ``sigma_px`` (full-resolution pixels), keyed by name in ``EFFECTS`` order."""
    leds = range(n_leds)
    effects = [
        Effect("core_light_leak", "light", tuple(
            [Param(f"amplitude_{m}", 0.0, 3.0, 0.0, "-", f"LED {m}'s light reaching the membrane through the core")
             for m in leds] + [Param("length_m", 0.002, 0.06, 0.015, "m", "distance at which it falls to half")]),
            "light from the LEDs travelling straight through the glass core and lighting the membrane from inside"),
        Effect("path_attenuation", "light", tuple(
            [Param(f"depth_{k}", 0.0, FADE_DEPTH_MAX, 0.0, "-",
                   f"optical depth the light gains over stretch {k} of {FADE_KNOTS} equal stretches of its distance "
                   "(from 0 to the longest distance the image circle holds)") for k in range(FADE_KNOTS)]
            + [Param("axial_share", 0.0, 1.0, 0.0, "-",
                     "which distance the light fades with: 0 its path over the membrane (from each LED for the LEDs' "
                     "own terms, from the LEDs' ring for the background), 1 the height along the sensor's axis above "
                     "the LEDs, in between a blend"),
               Param("led_weight", 0.0, 1.0, 1.0, "-", "share of the optical depth the LEDs' own terms take"),
               Param("ambient_weight", 0.0, 1.0, 1.0, "-",
                     "share of the optical depth the background term (the guided light it stands for) takes")]),
            "light fading along its way, by a monotone profile of a distance chosen by the data (over the membrane "
            "from the LEDs, or along the sensor's axis): absorption in the elastomer, or anything else that dims the "
            "light the farther it goes, on the LEDs' own terms and on the background as the data say"),
        Effect("membrane_compliance", "membrane", (
            Param("scale", 0.1, 1.3, 1.0, "-", "imprint depth / commanded depth"),),
            "the membrane and sensor yield under force, so imprints are weaker than commanded"),
        Effect("elastic_spread", "membrane", (
            Param("sigma_px", 0.5, 16.0, float(sigma_px), "px", "width of the elastic smoothing at full resolution"),),
            "a different elastic smoothing width"),
        Effect("coating_gloss", "light", (
            Param("k_g", 0.0, 3.0, 0.0, "-", "weight of the extra specular lobe"),
            Param("shininess", 2.0, 200.0, 30.0, "-", "its Phong exponent")),
            "specular behaviour of the paint beyond the simulator's"),
        Effect("contact_shadow", "light", (
            Param("elevation_rad", 0.02, 0.9, 0.2, "rad", "elevation of the arriving light above the surface"),
            Param("darkness", 0.0, 1.0, 0.0, "-", "share of the light a shadow removes")),
            "the indentation shadows light coming from an LED"),
        Effect("camera_response", "sensor", tuple(
            [Param(f"gain_{c}", 0.2, 3.0, 1.0, "-", f"{name} out of {name} in: the colour matrix's diagonal "
                   "(the white balance gain)") for c, name in zip(CHANNELS, ("red", "green", "blue"))]
            + [Param(f"mix_{o}{i}", -MIX_BOUND, MIX_BOUND, 0.0, "-", f"channel {i} in channel {o}'s output: "
                     "an off-diagonal of the colour matrix") for o, i in MIX_ENTRIES]
            + [Param("offset", -0.2, 0.2, 0.0, "-", "added to every channel before the curve (negative: a black "
                     "level taken off; positive: flare)"),
               Param("gamma", 0.3, 3.0, 1.0, "-", "the response curve out = y^(1/gamma)")]),
            "the camera's colour matrix (white balance and colour mixing, any 3x3), black level and response curve: "
            "out = clip(C in + offset)^(1/gamma)"),
        Effect("vignetting", "optics", tuple(
            [Param(f"depth_{k}", 0.0, VIGNETTE_DEPTH_MAX, 0.0, "-",
                   f"log fall-off over stretch {k} of {VIGNETTE_KNOTS} equal stretches of r = radius / focal "
                   "length, from the optical centre to the image circle's farthest pixel") for k in range(VIGNETTE_KNOTS)]
            + [Param("centre_du_px", -VIGNETTE_CENTRE_PX, VIGNETTE_CENTRE_PX, 0.0, "px", "optical centre offset, columns"),
               Param("centre_dv_px", -VIGNETTE_CENTRE_PX, VIGNETTE_CENTRE_PX, 0.0, "px", "optical centre offset, rows")]),
            "light falling off towards the image's edge by a monotone profile of the distance from an optical "
            "centre, V = exp(-sum_k depth_k ramp_k(r)): a lens's natural fall-off (cos^4), its mechanical "
            "vignetting, or a radial loss of any other form"),
        Effect("lens_distortion", "optics", (
            Param("k1", -0.6, 0.6, 0.0, "-", "radial coefficient of r^2, r = radius / focal length"),
            Param("k2", -0.4, 0.4, 0.0, "-", "radial coefficient of r^4")),
            "radial lens distortion (Brown-Conrady) the pinhole simulator leaves out"),
        Effect("misalignment", "optics", (
            Param("du_px", -60.0, 60.0, 0.0, "px", "shift, columns"), Param("dv_px", -60.0, 60.0, 0.0, "px", "shift, rows"),
            Param("rotation_rad", -math.pi, math.pi, 0.0, "rad", "rotation about the image centre"),
            Param("scale", 0.7, 1.4, 1.0, "-", "magnification"),
            Param("frame_share", 0.0, 1.0, 0.0, "-",
                  "share of the move that carries the image circle and the background too (0: the membrane and "
                  "LEDs turned against the camera, whose circle stays put; 1: the image itself moved)")),
            "real and simulated frames not registered"),
        Effect("blur_noise", "optics", (
            Param("sigma_px", 0.0, 6.0, 0.0, "px", "Gaussian blur at full resolution"),),
            "optics blur and sensor noise (the noise level is estimated from the residual, not fitted)"),
        Effect("led_spectrum", "light", tuple(
            [Param(f"shift_nm_{m}", -40.0, 40.0, 0.0, "nm", f"LED {m}'s peak shift") for m in leds]
            + [Param(f"power_{m}", 0.3, 3.0, 1.0, "-", f"LED {m}'s relative power") for m in leds]
            + [Param("filter_floor", 0.0, 0.15, FILTER_FLOOR_START, "-",
                     "out-of-band transmission of the colour filters, a share of their peak (acts only through "
                     "the shifts, so any value is the identity)")]),
            "LED spectra against the camera's spectral response"),
    ]
    return {e.name: e for e in effects}


# --- membrane -------------------------------------------------------------------------

def compliant_depth(ref: np.ndarray, depth: np.ndarray, scale: float) -> np.ndarray:
    """D' = D_ref - scale (D_ref - D): the imprint at ``scale`` of its commanded depth."""
    return ref - scale * (ref - depth)


def elastic_deform(depth: np.ndarray, ref: np.ndarray, sigma_px: float, truncate: float) -> np.ndarray:
    """D_def = min(D, D_ref - G_sigma * (D_ref - D)) with a Gaussian of ``sigma_px`` (at
    the map's own resolution), truncated at ``truncate`` sigmas, OpenCV's mirror border."""
    spread = ndimage.gaussian_filter(ref - depth, sigma_px, truncate=truncate, mode="mirror")
    return np.minimum(depth, ref - spread)


# --- light ----------------------------------------------------------------------------

def fade_ramps(distance_m: np.ndarray, length_m: float, knots: int = FADE_KNOTS) -> np.ndarray:
    """(K, ...) float32 the share of each of ``knots`` equal stretches of [0, length_m]
    that a distance covers: clip((d - t_k) / (t_{k+1} - t_k), 0, 1), t_k = k length / K."""
    d = np.asarray(distance_m, np.float32) * np.float32(knots / length_m)
    return np.stack([np.clip(d - np.float32(k), ZERO, ONE) for k in range(knots)])


def fade(ramps: np.ndarray, depths) -> np.ndarray:
    """exp(-tau(d)), tau = sum_k depth_k ramp_k(d): the light left after a distance whose
    ``fade_ramps`` are ``ramps`` (K, ...), with each stretch's optical depth ``depths``
    (K,) >= 0; monotone in d, and tau linear in d where every depth is equal (Beer-Lambert,
    mu = depth K / length)."""
    depths = np.asarray(depths, np.float32)
    return np.exp(-np.tensordot(depths, ramps, axes=1))


def fade_distances(path_m: np.ndarray, axial_m: np.ndarray, axial_share: float) -> np.ndarray:
    """(1 - s) path + s axial: the distance the light fades with (``path_attenuation``)."""
    return (1.0 - axial_share) * path_m + axial_share * axial_m


def leak_kernel(P: np.ndarray, N: np.ndarray, led_position, length_m: float) -> np.ndarray:
    """|N . w| / (1 + (d / lambda)^2): light from a source at ``led_position`` reaching
    surface points P (3, H, W) of normals N straight, d = |P - p|, w = (P - p) / d; the
    inverse-square law, finite at the source."""
    D = P - np.asarray(led_position, dtype=P.dtype).reshape(3, 1, 1)
    d2 = (D * D).sum(axis=0)
    return leak_kernel_from(np.abs((N * D).sum(axis=0)) / np.sqrt(np.maximum(d2, 1e-18)), d2, length_m)


def leak_kernel_from(cos: np.ndarray, d2: np.ndarray, length_m: float) -> np.ndarray:
    """``leak_kernel`` from its parts |N . w| and d^2 (which do not depend on lambda)."""
    return cos / (1.0 + d2 / (length_m * length_m))


#: contact_shadow: distances (m) from a receiving point, along the light's tangent, at
#: which the membrane ahead is looked up: geometric, 0.1 mm to 30 mm (a 1.5 mm imprint
#: lit at 3 degrees shadows 29 mm of a flat membrane).
SHADOW_STEPS_M = tuple(1e-4 * 1.15**k for k in range(42))
#: contact_shadow: the guided light arrives over elevations beta (1 -+ this), uniformly:
#: an extended source whose angular spread grows with its elevation.
SHADOW_SOURCE_SPREAD = 0.3


def occlusion_band(depth: np.ndarray, ref: np.ndarray, rays: np.ndarray, camera: tuple[float, float, float],
                   L: np.ndarray, inward: np.ndarray, where: np.ndarray,
                   moved_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Elevations of the guided light that the deformed membrane blocks, per LED and pixel.

    Light from LED m reaches a point x along the tangent t_m (the part of L_m in the
    undeformed tangent plane at x) tilted by an elevation beta towards the inside, in the
    plane of t_m and the inward normal n. March along t_m, s metres, and at each step
    find the membrane in that plane over the foot x + s t_m: the camera ray through the
    foot gives the surface point, which is moved along n onto the plane once (one
    fixed-point step). The deformed membrane there, at elevation atan2(h, s) above x's
    tangent plane, blocks the light below that elevation, unless the undeformed membrane
    rose higher before it: light at a lower elevation has come off the membrane nearer
    x (the GelTip's inside is concave), so an occluder farther on is not in its way.

    depth, ref : (H, W) deformed and no-contact planar depth, metres.
    rays : (3, H, W) camera rays, z = 1.  camera : (f, cx, cy), px.
    L : (M, 3, H, W) unit light vectors (towards the LED); inward : (3, H, W) unit
        inward normals of the undeformed membrane; where : (H, W) bool receivers.
    moved_m : a sample counts as the deformed membrane where it moved by more than this.

    Returns (low, high), (M, H, W) float32 radians: light between the two elevations is
    blocked (high <= low: none is; the pixels off ``where`` get an empty band).
    """
    import cv2

    f, cx, cy = camera
    h, w = depth.shape
    low = np.zeros((len(L), h, w), np.float32)
    high = np.zeros((len(L), h, w), np.float32)
    rows, cols = np.nonzero(where)
    if rows.size == 0 or not np.any(ref - depth > moved_m):
        return low, high
    depth, ref = np.asarray(depth, np.float32), np.asarray(ref, np.float32)
    moved = ref - depth
    # The deformed membrane's bounding sphere: a receiver whose light plane misses it, or
    # that has it behind, cannot be shadowed, and its march ends past it.
    occluder = (depth * rays)[:, moved > moved_m]  # (3, K_o)
    centre = 0.5 * (occluder.min(axis=1) + occluder.max(axis=1))
    radius = 0.5 * float(np.linalg.norm(occluder.max(axis=1) - occluder.min(axis=1))) + SHADOW_STEPS_M[0]
    P = depth[rows, cols] * rays[:, rows, cols]  # (3, K) receiving points, float32
    n = inward[:, rows, cols].astype(np.float32)
    inside = where.astype(np.float32)

    def lookup(image: np.ndarray, u: np.ndarray, v: np.ndarray, nearest: bool = False) -> np.ndarray:
        """``image`` (H, W) float32 at (u, v) px: bilinear, edge replicated (OpenCV's remap,
        much faster than scipy's on scattered points); nearest: 0 outside."""
        mode, border = (cv2.INTER_NEAREST, cv2.BORDER_CONSTANT) if nearest else (cv2.INTER_LINEAR, cv2.BORDER_REPLICATE)
        count, width = u.size, 1024  # remap wants maps under 32767 px a side: fold the points
        pad = -count % width
        maps = [np.pad(x, (0, pad), constant_values=-1.0).reshape(-1, width) for x in (u, v)]
        return cv2.remap(image, maps[0], maps[1], mode, borderMode=border, borderValue=0).reshape(-1)[:count]

    def pixel(G: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        z = np.maximum(G[2], 1e-9)
        return cx + f * G[0] / z, cy + f * G[1] / z

    def elevation(F, u, v, which, P, t, n) -> np.ndarray:
        """Elevation (rad) above P's tangent plane of the surface of ``which`` in the
        light's plane over the feet F (3, K), whose pixels are (u, v)."""
        d = lookup(which, u, v)  # the surface on the camera ray through the foot...
        Q = np.stack([d * (u - cx) / f, d * (v - cy) / f, d])
        u, v = pixel(F + ((Q - F) * n).sum(axis=0) * n)  # ... and on the ray through its height over the foot
        d = lookup(which, u, v)
        a = np.stack([d * (u - cx) / f, d * (v - cy) / f, d]) - P
        return np.arctan2((a * n).sum(axis=0), (a * t).sum(axis=0))

    for m, L_m in enumerate(L):
        t = L_m[:, rows, cols].astype(np.float32)
        t -= (t * n).sum(axis=0) * n
        norm = np.linalg.norm(t, axis=0)
        t /= np.maximum(norm, 1e-12)
        to_centre = centre[:, None] - P
        ahead = (to_centre * t).sum(axis=0)  # how far along t the occluder's centre lies
        side = np.abs((to_centre * np.cross(t, n, axis=0)).sum(axis=0))
        idx = np.flatnonzero((norm > 1e-6) & (ahead > -radius) & (side < radius))
        reach = ahead[idx] + radius  # past this, the march has left the occluder behind
        P_m, n_m, t_m = P[:, idx], n[:, idx], t[:, idx]
        rise = np.full(idx.size, -np.inf, np.float32)  # highest elevation of the undeformed membrane so far
        lo = np.full(idx.size, np.inf, np.float32)
        hi = np.full(idx.size, -np.inf, np.float32)
        k = np.arange(idx.size)  # the receivers still marching
        for s in SHADOW_STEPS_M:
            keep = s <= reach[k]
            if not keep.all():
                k = k[keep]
            if k.size == 0:
                break
            Pk, tk, nk = P_m[:, k], t_m[:, k], n_m[:, k]
            F = Pk + np.float32(s) * tk
            u, v = pixel(F)
            ok = (F[2] > 1e-9) & (lookup(inside, u, v, nearest=True) > 0)  # else: left the image circle
            up = elevation(F, u, v, depth, Pk, tk, nk)
            up_ref = elevation(F, u, v, ref, Pk, tk, nk)
            block = ok & (lookup(moved, u, v) > moved_m) & (up > rise[k])
            lo[k] = np.where(block, np.minimum(lo[k], rise[k]), lo[k])
            hi[k] = np.where(block, np.maximum(hi[k], up), hi[k])
            rise[k] = np.where(ok, np.maximum(rise[k], up_ref), rise[k])
            k = k[ok]
        blocked = hi > lo
        low[m, rows[idx], cols[idx]] = np.where(blocked, np.maximum(lo, 0.0), 0.0)
        high[m, rows[idx], cols[idx]] = np.where(blocked, np.maximum(hi, 0.0), 0.0)
    return low, high


def shadow_factor(low: np.ndarray, high: np.ndarray, elevation_rad: float, darkness: float,
                  spread: float = SHADOW_SOURCE_SPREAD) -> np.ndarray:
    """Light left, 1 - darkness * b: b the share of a source spread uniformly over
    elevations beta (1 -+ spread) that falls in the blocked band (low, high], radians."""
    b0, b1 = elevation_rad * (1.0 - spread), elevation_rad * (1.0 + spread)
    blocked = np.clip((np.minimum(high, b1) - np.maximum(low, b0)) / (b1 - b0), 0.0, 1.0)
    return (1.0 - darkness * blocked).astype(np.float32)


#: led_spectrum: where the fit starts the colour filters' out-of-band transmission, a
#: share of their peak (absorbing dyes of CMOS Bayer filters pass a few per cent outside
#: their band).
FILTER_FLOOR_START = 0.03


def spectral_colours(colours: np.ndarray, peaks_nm, fwhms_nm, shifts_nm, powers, floor: float = 0.0) -> np.ndarray:
    """Each LED's colour with its peak shifted and its power scaled, through the camera's
    spectral response R: c'_m = power_m c_m R(peak_m + shift_m) / R(peak_m), channel-wise.

    Channel c's filter passes S_c = G_c + floor, its Gaussian band G_c (unit peak) over a
    flat out-of-band transmission ``floor``, a share of the peak: R_c(p) = int G_c E_p +
    floor int E_p, E_p the LED's spectrum peaking at p. The floor term keeps the ratio of a
    channel deep in the Gaussian's tail finite (a pure Gaussian band makes the blue
    response to a red LED jump by a factor of ten for a 15 nm shift).

    Uses the reference's camera bands (``pbr_tactile.spectra``, numpy only).
    """
    from pbr_tactile.spectra import WAVELENGTHS_NM, film_response, gaussian

    out = np.array(colours, dtype=np.float64)
    for m, (peak, fwhm, shift, power) in enumerate(zip(peaks_nm, fwhms_nm, shifts_nm, powers)):
        if shift:
            before, after = gaussian(peak, fwhm), gaussian(peak + shift, fwhm)
            flat_before = floor * np.trapezoid(before, WAVELENGTHS_NM)
            flat_after = floor * np.trapezoid(after, WAVELENGTHS_NM)
            ratio = (film_response(after) + flat_after) / np.maximum(film_response(before) + flat_before, 1e-12)
            out[m] = out[m] * ratio
        out[m] = out[m] * power
    return out


# --- optics and sensor ------------------------------------------------------------------

def source_coordinates(shape: tuple[int, int], f: float, centre: tuple[float, float], misalignment: dict | None,
                       distortion: dict | None) -> np.ndarray:
    """For each output (real) pixel, where to sample the simulated image: (2, H, W) (row, col).

    Lens distortion first maps a distorted (real) pixel to the undistorted one: Brown's
    r_d = r_u (1 + k1 r_u^2 + k2 r_u^4), r = |x - c| / f, inverted
    (``scenes.camera.undistorted_radius``: the reference's lens, ``pbr_tactile.sensor``,
    has the same k1 and k2); misalignment then maps it into the simulated frame by a
    similarity about the image centre: x_s = c + scale R(theta) (x_u - c) + (du, dv).
    Pixels no ray reaches (past a strong barrel's fold) sample outside the image.
    """
    from scenes.camera import undistortion_stretch

    h, w = shape
    cv, cu = centre
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    y, x = v - cv, u - cu
    if distortion is not None:
        stretch = undistortion_stretch(np.hypot(x, y) / f, distortion["k1"], distortion["k2"])
        x, y = x * stretch, y * stretch
    if misalignment is not None:
        c, s = math.cos(misalignment["rotation_rad"]), math.sin(misalignment["rotation_rad"])
        sc = misalignment["scale"]
        x, y = sc * (c * x - s * y) + misalignment["du_px"], sc * (s * x + c * y) + misalignment["dv_px"]
    coords = np.stack([y + cv, x + cu])
    return coords if distortion is None else np.nan_to_num(coords, nan=-2.0)


def misalign_membrane(images: np.ndarray, coords: np.ndarray, fixed: np.ndarray, circle: np.ndarray,
                      frame_share: float) -> np.ndarray:
    """Images whose membrane moved against the camera: the part that belongs to the
    membrane and LEDs, images - fixed, is resampled at ``coords`` and seen through the
    fixed image ``circle``, while ``fixed`` (what the camera and lens add: the background
    term of a real no-contact capture, already in the real frame) stays put; blended with
    the whole frame resampled, by ``frame_share``.

    images : (N, H, W, 3); coords : (2, H, W) as ``source_coordinates``; fixed : (H, W, 3)
    linear RGB; circle : (H, W) in [0, 1], the share of each pixel inside the image circle.
    """
    moved = fixed + resample(images - fixed, coords) * circle[..., None]
    if frame_share <= 0.0:
        return moved
    return ((1.0 - frame_share) * moved + frame_share * resample(images, coords)).astype(np.float32)


def resample(images: np.ndarray, coords: np.ndarray) -> np.ndarray:
    """Sample (N, H, W, 3) images at (2, H, W) coordinates, bilinear, zero outside
    (OpenCV's remap)."""
    import cv2

    map_x = np.ascontiguousarray(coords[1], dtype=np.float32)
    map_y = np.ascontiguousarray(coords[0], dtype=np.float32)
    out = np.empty_like(images, dtype=np.float32)
    for i in range(len(images)):
        out[i] = cv2.remap(np.ascontiguousarray(images[i], dtype=np.float32), map_x, map_y, cv2.INTER_LINEAR,
                           borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    return out


def radial_distance(shape: tuple[int, int], f: float, centre: tuple[float, float]) -> np.ndarray:
    """(H, W) float32 r = distance from ``centre`` (row, col) px / f."""
    h, w = shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)
    return (np.hypot(u - np.float32(centre[1]), v - np.float32(centre[0])) / np.float32(f)).astype(np.float32)


def vignette_length(mask: np.ndarray, f: float, factor: int = 1) -> float:
    """The span of ``vignetting``'s profile in r: the image circle's farthest pixel from
    the image centre, over f, plus the centre's largest offset (``VIGNETTE_CENTRE_PX`` at
    full resolution; ``factor`` the images' downsampling)."""
    h, w = mask.shape
    r = radial_distance(mask.shape, f, ((h - 1) / 2, (w - 1) / 2))
    return float(r[mask].max(initial=0.0)) + VIGNETTE_CENTRE_PX / (f * factor)


def vignette(shape: tuple[int, int], f: float, centre: tuple[float, float], depths, length: float) -> np.ndarray:
    """V = exp(-sum_k depth_k ramp_k(r)), r = distance from the optical centre / f, over
    ``len(depths)`` equal stretches of [0, ``length``] (``fade_ramps``); (H, W) float32."""
    depths = np.asarray(depths, np.float32)
    return fade(fade_ramps(radial_distance(shape, f, centre), length, len(depths)), depths).astype(np.float32)


def blur(images: np.ndarray, sigma_px: float) -> np.ndarray:
    """Gaussian blur of each channel of (N, H, W, 3) images, sigma in the images' pixels
    (OpenCV, kernel to 4 sigma, replicated border)."""
    if sigma_px <= 0:
        return images
    import cv2

    out = np.empty_like(images, dtype=np.float32)
    for i in range(len(images)):
        out[i] = cv2.GaussianBlur(np.ascontiguousarray(images[i], dtype=np.float32), (0, 0), sigma_px,
                                  borderType=cv2.BORDER_REPLICATE)
    return out


def colour_matrix(params: dict) -> np.ndarray:
    """(3, 3) colour matrix C of camera_response's parameters, out = C in: the gains on
    the diagonal, ``mix_<out><in>`` off it."""
    C = np.diag([params[f"gain_{c}"] for c in CHANNELS]).astype(np.float64)
    for o, i in MIX_ENTRIES:
        C[CHANNELS.index(o), CHANNELS.index(i)] = params[f"mix_{o}{i}"]
    return C


def camera_response(images: np.ndarray, matrix: np.ndarray, offset: float, gamma: float) -> np.ndarray:
    """out = clip(C in + offset, 0, 1)^(1 / gamma), C the (3, 3) colour matrix.

    images : (..., 3) float linear RGB; matrix : C, out = C in; offset : added to every
    channel (a black level, negative, or flare, positive); gamma : of the response curve.
    Returns images' shape, float32.
    """
    images = np.asarray(images, np.float32)
    # one (K, 3) @ (3, 3) product: numpy's batched matmul over (N, H, W, 3) is 3x slower
    mixed = (images.reshape(-1, 3) @ np.asarray(matrix, np.float64).T.astype(np.float32)).reshape(images.shape)
    if offset:
        mixed += np.float32(offset)
    mixed = np.clip(mixed, ZERO, ONE)
    return mixed if gamma == 1.0 else np.power(mixed, np.float32(1.0 / gamma))


def noise_std(residual: np.ndarray, mask: np.ndarray) -> float:
    """Sensor noise estimated from residuals (N, H, W, 3): the spread of differences of
    horizontally adjacent pixels, / sqrt(2) (smooth model errors cancel there, white
    noise does not), with the median absolute deviation for robustness."""
    d = np.diff(residual, axis=2)[:, mask[:, 1:] & mask[:, :-1]]
    if d.size == 0:
        return 0.0
    mad = np.median(np.abs(d - np.median(d)))
    return float(1.4826 * mad / math.sqrt(2.0))
