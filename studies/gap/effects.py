"""The catalogue of candidate unmodelled effects, and each one's physical model.

Every effect is a parametric stage that can be added to the fast simulator
(``studies.gap.model.FastModel`` composes them). Its parameters have bounds, an identity
value (where the effect is absent) and units; the diagnosis fits them on training samples.
The functions here are pure array functions, in the simulator's order:

1. membrane: ``membrane_compliance`` (the imprint is shallower than commanded),
   ``elastic_spread`` (another width of the elastic smoothing);
2. light and paint, per LED m: ``path_attenuation`` (absorption along the geodesic
   path from the LED, I_m exp(-mu g_m)), ``contact_shadow`` (the dent's rim hides the
   light arriving along the field; horizon test on the indentation height field),
   ``coating_gloss`` (an extra specular lobe k_g (R_m . V)^alpha_g), ``core_light_leak``
   (light crossing the glass core straight from each LED: a_m |N . w_m| / (1 + (d_m /
   lambda)^2)), ``led_spectrum`` (each LED's peak shifted and its power scaled, seen
   through the camera's spectral response);
3. optics and sensor: ``misalignment`` and ``lens_distortion`` (one resampling of the
   image; a misalignment moves the membrane's image under the lens's fixed image circle
   and background, or, at ``frame_share`` 1, the whole frame), ``vignetting`` (1 / (1 + a r^2 + b r^4)), ``blur_noise`` (Gaussian blur; the
   noise is estimated, not added, since a prediction is a mean), ``camera_response``
   (white balance, colour cross-talk, gamma).
"""

from __future__ import annotations

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


def catalogue(n_leds: int, sigma_px: float) -> dict[str, Effect]:
    """The effects for a sensor with ``n_leds`` LEDs whose elastic smoothing has width
    ``sigma_px`` (full-resolution pixels), keyed by name in ``EFFECTS`` order."""
    leds = range(n_leds)
    effects = [
        Effect("core_light_leak", "light", tuple(
            [Param(f"amplitude_{m}", 0.0, 3.0, 0.0, "-", f"LED {m}'s light reaching the membrane through the core")
             for m in leds] + [Param("length_m", 0.002, 0.06, 0.015, "m", "distance at which it falls to half")]),
            "light from the LEDs travelling straight through the glass core and lighting the membrane from inside"),
        Effect("path_attenuation", "light", (
            Param("mu_per_m", 0.0, 250.0, 0.0, "1/m", "absorption coefficient along the geodesic path"),),
            "absorption along the light's path in the elastomer (geodesic distance from each LED)"),
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
        Effect("camera_response", "sensor", (
            Param("gain_r", 0.3, 3.0, 1.0, "-", "red gain"), Param("gain_g", 0.3, 3.0, 1.0, "-", "green gain"),
            Param("gain_b", 0.3, 3.0, 1.0, "-", "blue gain"),
            Param("gamma", 0.3, 3.0, 1.0, "-", "out = in^(1/gamma)"),
            Param("crosstalk", 0.0, 0.4, 0.0, "-", "share of each channel leaking into the other two")),
            "the camera's gamma, white balance and colour mixing"),
        Effect("vignetting", "optics", (
            Param("a", 0.0, 6.0, 0.0, "-", "r^2 coefficient, r = radius / focal length"),
            Param("b", 0.0, 6.0, 0.0, "-", "r^4 coefficient"),
            Param("centre_du_px", -40.0, 40.0, 0.0, "px", "optical centre offset, columns"),
            Param("centre_dv_px", -40.0, 40.0, 0.0, "px", "optical centre offset, rows")),
            "light falling off towards the image's edge, V = 1 / (1 + a r^2 + b r^4)"),
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
            + [Param(f"power_{m}", 0.3, 3.0, 1.0, "-", f"LED {m}'s relative power") for m in leds]),
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

def attenuation(geodesic_m: np.ndarray, mu_per_m: float) -> np.ndarray:
    """exp(-mu g): the share of an LED's light left after a geodesic path of g metres."""
    return np.exp(-mu_per_m * geodesic_m)


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


def image_directions(P: np.ndarray, L: np.ndarray, f: float) -> tuple[np.ndarray, np.ndarray]:
    """Where a 3D direction L (3, H, W) at points P (3, H, W) points in the image.

    Returns the unit image direction (2, H, W) as (d_row, d_col) and the pixels moved per
    metre travelled along L (H, W).
    """
    z = np.maximum(P[2], 1e-9)
    du = f * (L[0] * z - P[0] * L[2]) / (z * z)
    dv = f * (L[1] * z - P[1] * L[2]) / (z * z)
    speed = np.sqrt(du * du + dv * dv)
    safe = np.maximum(speed, 1e-12)
    return np.stack([dv / safe, du / safe]), speed


#: Steps (px at the map's resolution) at which ``horizon`` looks towards the light.
HORIZON_STEPS_PX = (1, 2, 3, 4, 6, 8, 11, 15, 20, 26, 34, 44)


def horizon(delta: np.ndarray, direction: np.ndarray, px_per_m: np.ndarray, where: np.ndarray) -> np.ndarray:
    """Steepest rise of the surface towards the light, as a slope (m/m), at ``where``.

    delta : (H, W) indentation D_ref - D_def, metres (how far the surface was pushed
        away from the camera); direction (2, H, W) unit image direction towards the
        light; px_per_m (H, W). A point inside a dent sees the rim between it and the
        light rise by delta(x) - delta(x + t u) over t / px_per_m metres; the light,
        arriving at a low elevation, is blocked where that slope exceeds its tangent.
    Returns (H, W) slopes, 0 outside ``where``.
    """
    rows, cols = np.nonzero(where)
    out = np.zeros(delta.shape, np.float32)
    if len(rows) == 0:
        return out
    d0 = delta[rows, cols]
    dr, dc = direction[0][rows, cols], direction[1][rows, cols]
    metres_per_px = 1.0 / np.maximum(px_per_m[rows, cols], 1e-6)
    best = np.zeros(len(rows), np.float32)
    for t in HORIZON_STEPS_PX:
        ahead = ndimage.map_coordinates(delta, [rows + t * dr, cols + t * dc], order=1, mode="nearest")
        best = np.maximum(best, (d0 - ahead) / (t * metres_per_px))
    out[rows, cols] = best
    return out


def shadow_factor(slope: np.ndarray, elevation_rad: float, darkness: float) -> np.ndarray:
    """Light left, 1 - darkness * smoothstep: shadowed where the rim's slope exceeds
    tan(elevation), with a soft edge as wide as tan(elevation) / 2."""
    t = math.tan(elevation_rad)
    x = np.clip((slope - t) / (0.5 * t + 1e-6), 0.0, 1.0)
    return 1.0 - darkness * x * x * (3.0 - 2.0 * x)


def spectral_colours(colours: np.ndarray, peaks_nm, fwhms_nm, shifts_nm, powers) -> np.ndarray:
    """Each LED's colour with its peak shifted and its power scaled, through the camera's
    spectral response R: c'_m = power_m c_m R(peak_m + shift_m) / R(peak_m), channel-wise.

    Uses the reference's camera bands (``pbr_tactile.spectra``, numpy only).
    """
    from pbr_tactile.spectra import film_response, gaussian

    out = np.array(colours, dtype=np.float64)
    for m, (peak, fwhm, shift, power) in enumerate(zip(peaks_nm, fwhms_nm, shifts_nm, powers)):
        if shift:
            ratio = film_response(gaussian(peak + shift, fwhm)) / np.maximum(film_response(gaussian(peak, fwhm)), 1e-12)
            out[m] = out[m] * ratio
        out[m] = out[m] * power
    return out


# --- optics and sensor ------------------------------------------------------------------

def source_coordinates(shape: tuple[int, int], f: float, centre: tuple[float, float], misalignment: dict | None,
                       distortion: dict | None) -> np.ndarray:
    """For each output (real) pixel, where to sample the simulated image: (2, H, W) (row, col).

    Lens distortion first maps a distorted (real) pixel to the undistorted one, x_u = c +
    (x_d - c)(1 + k1 r^2 + k2 r^4), r = |x_d - c| / f; misalignment then maps it into the
    simulated frame by a similarity about the image centre: x_s = c + scale R(theta)
    (x_u - c) + (du, dv).
    """
    h, w = shape
    cv, cu = centre
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    y, x = v - cv, u - cu
    if distortion is not None:
        r2 = (x * x + y * y) / (f * f)
        k = 1.0 + distortion["k1"] * r2 + distortion["k2"] * r2 * r2
        x, y = x * k, y * k
    if misalignment is not None:
        c, s = math.cos(misalignment["rotation_rad"]), math.sin(misalignment["rotation_rad"])
        sc = misalignment["scale"]
        x, y = sc * (c * x - s * y) + misalignment["du_px"], sc * (s * x + c * y) + misalignment["dv_px"]
    return np.stack([y + cv, x + cu])


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


def vignette(shape: tuple[int, int], f: float, centre: tuple[float, float], a: float, b: float) -> np.ndarray:
    """V = 1 / (1 + a r^2 + b r^4), r = distance from the optical centre / f; (H, W)."""
    h, w = shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    r2 = ((u - centre[1]) ** 2 + (v - centre[0]) ** 2) / (f * f)
    return (1.0 / (1.0 + a * r2 + b * r2 * r2)).astype(np.float32)


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


def camera_response(images: np.ndarray, gains, gamma: float, crosstalk: float) -> np.ndarray:
    """out = clip(gains * (C in))^(1 / gamma), C = (1 - crosstalk) I + crosstalk / 2 (J - I)."""
    C = np.full((3, 3), crosstalk / 2.0)
    np.fill_diagonal(C, 1.0 - crosstalk)
    mixed = images @ (C.T * np.asarray(gains, dtype=np.float64)[None, :]).astype(images.dtype)
    mixed = np.clip(mixed, 0.0, 1.0)
    return mixed if gamma == 1.0 else np.power(mixed, 1.0 / gamma)


def noise_std(residual: np.ndarray, mask: np.ndarray) -> float:
    """Sensor noise estimated from residuals (N, H, W, 3): the spread of differences of
    horizontally adjacent pixels, / sqrt(2) (smooth model errors cancel there, white
    noise does not), with the median absolute deviation for robustness."""
    d = np.diff(residual, axis=2)[:, mask[:, 1:] & mask[:, :-1]]
    if d.size == 0:
        return 0.0
    mad = np.median(np.abs(d - np.median(d)))
    return float(1.4826 * mad / math.sqrt(2.0))
