"""Gap mechanisms written from prose descriptions alone: the blind benchmark's third source.

Each mechanism here was written by another hand from the one-paragraph description of a
physical effect kept beside it in ``DESCRIPTIONS``, without reading the catalogue of
candidate effects (``studies.gap.effects``) or the benchmark's other injectors, so that
its functional form is the description's and not the catalogue's. A correct diagnosis of
an image made by mechanism ``m`` should rank the catalogue effect ``MECHANISMS[m]`` first.
The fitter and its tests never import this module, and it imports nothing from
``studies.gap``.

Use::

    described = Described(spec, ref_depth)
    params = sample_params("lens_falloff", strength, rng)
    real = described.apply(image, "lens_falloff", params)

Images are (H, W, 3) float32 linear RGB in [0, 1]; depths (H, W) metres, planar z-depth;
pixel (u, v) has its centre at integer coordinates (u right, v down).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable, Mapping

import cv2
import numpy as np

from scenes.camera import Camera, back_project, check_depth
from scenes.spec import SensorSpec

# --- What each mechanism stands for ---------------------------------------------------------

#: Mechanism -> the catalogue effect a correct diagnosis should rank first.
MECHANISMS: dict[str, str] = {
    "gamma_mix_gains": "camera_response",
    "axial_fade": "path_attenuation",
    "lens_falloff": "vignetting",
    "defocus": "blur_noise",
    "seat_offset": "misalignment",
    "barrel_lens": "lens_distortion",
    "soft_membrane": "membrane_compliance",
}

#: Mechanism -> the simulator background its cases are rendered on.
BACKGROUNDS: dict[str, str] = {
    "gamma_mix_gains": "solid",
    "axial_fade": "solid",
    "lens_falloff": "solid",
    "defocus": "solid",
    "seat_offset": "real",
    "barrel_lens": "real",
    "soft_membrane": "solid",
}

#: Mechanism -> the prose it was written from.
DESCRIPTIONS: dict[str, str] = {
    "gamma_mix_gains": (
        "A camera whose response is not the simulator's, over the whole frame: one gamma curve "
        "applied to all channels (the exponent about 1 +- 0.4: strength 0 gives |1 - gamma| about "
        "0.15, strength 1 about 0.4, sign drawn), then a 3x3 channel mix whose off-diagonal terms "
        "are up to about +-0.1 (each drawn uniformly within +- a bound growing with strength from "
        "0.03 to 0.1; diagonal 1), then a gain per channel of about 1 +- 0.2 (each drawn within +- "
        "a bound growing from 0.08 to 0.2)."
    ),
    "axial_fade": (
        "Light that fades with distance up the tube: the whole image, background included, times "
        "exp(-mu * max(0, z - z0)), with z the undeformed membrane's height along the sensor's "
        "axis (the camera frame's z of the no-contact surface point each pixel sees), z0 = 20 mm, "
        "mu from about 15 per metre (strength 0) to about 45 per metre (strength 1)."
    ),
    "lens_falloff": (
        "Natural light fall-off of a wide lens: each pixel is scaled by cos(theta)^4, theta the "
        "angle between the pixel's ray and an optical axis that is slightly off the image centre "
        "(by up to a few pixels, drawn), with the lens's focal length in pixels scaled by a factor "
        "(strength 0: 1.6 times the camera's f, a mild fall-off; strength 1: 1.0 times f, a "
        "strong one)."
    ),
    "defocus": (
        "The camera slightly out of focus: each channel convolved with a uniform disc (pillbox) "
        "of radius 1.5 px (strength 0) to 4 px (strength 1), edges replicated."
    ),
    "seat_offset": (
        "The camera seated off-centre in the tube and turned: the whole image shifted by 3 to 10 "
        "px (strength 0 to 1, direction drawn) and rotated about the image centre by 1 to 4 "
        "degrees (sign drawn), resampled bilinearly; black where nothing maps."
    ),
    "barrel_lens": (
        "A lens with barrel or pincushion distortion the pinhole simulator lacks: written as a "
        "division model, a real pixel at normalised radius r_d (distance from the image centre "
        "divided by f) shows the simulated pixel at r_u = r_d / (1 + lambda r_d^2), lambda from "
        "+-0.05 (strength 0) to +-0.25 (strength 1), sign drawn; bilinear resampling, black "
        "outside."
    ),
    "soft_membrane": (
        "The membrane yields under the indenter, so every imprint is shallower than commanded: "
        "the contact's indentation (ref_depth - depth, where positive) is multiplied by a factor "
        "from 0.75 (strength 0) to 0.4 (strength 1) and the contact re-rendered by the plain "
        "simulator (`render`)."
    ),
}

# --- Ranges: (strength 0, strength 1) pairs, linear in between ------------------------------

#: |1 - gamma| of the camera's response curve.
GAMMA_DEVIATION = (0.15, 0.40)
#: Bound of each off-diagonal term of the 3x3 channel mix (drawn uniformly within +-).
MIX_OFFDIAGONAL_BOUND = (0.03, 0.10)
#: Bound of each channel gain's deviation from 1 (drawn uniformly within +-).
GAIN_DEVIATION_BOUND = (0.08, 0.20)

#: Height along the sensor's axis (camera-frame z) where the axial fade begins, metres.
FADE_START_M = 0.020
#: Attenuation coefficient of the axial fade, 1/m.
FADE_MU_PER_M = (15.0, 45.0)

#: The fall-off lens' focal length, in units of the camera's f (shorter: stronger fall-off).
FALLOFF_FOCAL_SCALE = (1.6, 1.0)
#: Largest offset of the fall-off's optical axis from the image centre, px (drawn, any
#: direction, uniformly in magnitude).
FALLOFF_AXIS_OFFSET_PX = 4.0

#: Radius of the defocus pillbox, px.
DEFOCUS_RADIUS_PX = (1.5, 4.0)
#: Sub-samples per pixel side when the pillbox's pixel coverage is computed: its area then
#: matches pi r^2 to well under 1 %, where a binary disc is off by up to 30 % at 1.5 px.
PILLBOX_SUPERSAMPLE = 16

#: Length of the camera's seat shift, px.
SEAT_SHIFT_PX = (3.0, 10.0)
#: Magnitude of the camera's turn about the image centre, degrees.
SEAT_ROTATION_DEG = (1.0, 4.0)

#: |lambda| of the division-model distortion (lambda > 0: pincushion, < 0: barrel).
DIVISION_LAMBDA = (0.05, 0.25)

#: Share of the commanded indentation the soft membrane keeps.
SOFT_FACTOR = (0.75, 0.40)

#: The parameters each mechanism's ``apply`` needs (what ``sample_params`` returns).
PARAM_NAMES: dict[str, tuple[str, ...]] = {
    "gamma_mix_gains": ("gamma", "mix_rg", "mix_rb", "mix_gr", "mix_gb", "mix_br", "mix_bg",
                        "gain_r", "gain_g", "gain_b"),
    "axial_fade": ("mu_per_m", "z0_m"),
    "lens_falloff": ("focal_scale", "axis_dx_px", "axis_dy_px"),
    "defocus": ("radius_px",),
    "seat_offset": ("shift_x_px", "shift_y_px", "rotation_deg"),
    "barrel_lens": ("lambda",),
    "soft_membrane": ("factor",),
}

#: The channel letters of the mix's parameter names: ``mix_<out><in>``.
_CHANNELS = "rgb"


# --- Validation -----------------------------------------------------------------------------

def _check_mechanism(mechanism) -> str:
    if not isinstance(mechanism, str) or mechanism not in MECHANISMS:
        raise ValueError(f"mechanism must be one of {sorted(MECHANISMS)}, got {mechanism!r}")
    return mechanism


def _check_strength(strength) -> float:
    # bool is an int subclass: refuse it explicitly, True is not a strength.
    if isinstance(strength, bool) or not isinstance(strength, numbers.Real) or not (0.0 <= float(strength) <= 1.0):
        raise ValueError(f"strength must be a float in [0, 1], got {strength!r}")
    return float(strength)


def _check_params(mechanism: str, params) -> dict[str, float]:
    if not isinstance(params, Mapping):
        raise ValueError(f"params must be a mapping of {PARAM_NAMES[mechanism]}, got {type(params).__name__}")
    wanted = PARAM_NAMES[mechanism]
    missing = [k for k in wanted if k not in params]
    extra = [k for k in params if k not in wanted]
    if missing or extra:
        raise ValueError(f"params of {mechanism} must be exactly {list(wanted)}; "
                         f"missing {missing}, unexpected {extra}")
    out = {}
    for k in wanted:
        v = params[k]
        if isinstance(v, bool) or not isinstance(v, numbers.Real) or not math.isfinite(float(v)):
            raise ValueError(f"params[{k!r}] must be a finite float, got {v!r}")
        out[k] = float(v)
    return out


def _lerp(pair: tuple[float, float], strength: float) -> float:
    return pair[0] + (pair[1] - pair[0]) * strength


# --- Parameters -----------------------------------------------------------------------------

def sample_params(mechanism: str, strength: float, rng: np.random.Generator) -> dict[str, float]:
    """Draw one mechanism's parameters at a strength.

    Parameters
    ----------
    mechanism : str
        One of ``MECHANISMS``.
    strength : float
        In [0, 1]: 0 is weak but clearly visible, 1 strong; magnitudes are linear in it
        between the module's (strength 0, strength 1) pairs.
    rng : numpy.random.Generator
        Source of the signs, directions and per-term draws. Each mechanism draws the same
        numbers in the same order whatever the strength, so one seed gives the same
        signs and directions at every strength.

    Returns
    -------
    dict[str, float]
        ``PARAM_NAMES[mechanism]`` -> value, SI units or pixels as the names say.
    """
    mechanism = _check_mechanism(mechanism)
    s = _check_strength(strength)
    if not isinstance(rng, np.random.Generator):
        raise ValueError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")

    if mechanism == "gamma_mix_gains":
        sign = 1.0 if rng.random() < 0.5 else -1.0
        u_mix = rng.uniform(-1.0, 1.0, 6)
        u_gain = rng.uniform(-1.0, 1.0, 3)
        params = {"gamma": 1.0 + sign * _lerp(GAMMA_DEVIATION, s)}
        off = [(o, i) for o in range(3) for i in range(3) if o != i]
        bound = _lerp(MIX_OFFDIAGONAL_BOUND, s)
        for (o, i), u in zip(off, u_mix):
            params[f"mix_{_CHANNELS[o]}{_CHANNELS[i]}"] = float(bound * u)
        bound = _lerp(GAIN_DEVIATION_BOUND, s)
        for c, u in zip(_CHANNELS, u_gain):
            params[f"gain_{c}"] = float(1.0 + bound * u)
        return params
    if mechanism == "axial_fade":
        return {"mu_per_m": _lerp(FADE_MU_PER_M, s), "z0_m": FADE_START_M}
    if mechanism == "lens_falloff":
        angle = rng.uniform(0.0, 2.0 * math.pi)
        offset = FALLOFF_AXIS_OFFSET_PX * rng.random()
        return {"focal_scale": _lerp(FALLOFF_FOCAL_SCALE, s),
                "axis_dx_px": float(offset * math.cos(angle)), "axis_dy_px": float(offset * math.sin(angle))}
    if mechanism == "defocus":
        return {"radius_px": _lerp(DEFOCUS_RADIUS_PX, s)}
    if mechanism == "seat_offset":
        angle = rng.uniform(0.0, 2.0 * math.pi)
        sign = 1.0 if rng.random() < 0.5 else -1.0
        shift = _lerp(SEAT_SHIFT_PX, s)
        return {"shift_x_px": float(shift * math.cos(angle)), "shift_y_px": float(shift * math.sin(angle)),
                "rotation_deg": sign * _lerp(SEAT_ROTATION_DEG, s)}
    if mechanism == "barrel_lens":
        sign = 1.0 if rng.random() < 0.5 else -1.0
        return {"lambda": sign * _lerp(DIVISION_LAMBDA, s)}
    # soft_membrane
    return {"factor": _lerp(SOFT_FACTOR, s)}


# --- Pure helpers: arrays in, arrays out ----------------------------------------------------

def mix_matrix(params: Mapping[str, float]) -> np.ndarray:
    """The (3, 3) channel mix of ``gamma_mix_gains`` parameters: 1 on the diagonal and
    ``params["mix_<out><in>"]`` off it (row: output channel, column: input channel)."""
    m = np.eye(3)
    for o in range(3):
        for i in range(3):
            if o != i:
                m[o, i] = params[f"mix_{_CHANNELS[o]}{_CHANNELS[i]}"]
    return m


def camera_response(image: np.ndarray, gamma: float, mix: np.ndarray, gains: np.ndarray) -> np.ndarray:
    """A camera response: ``gains * (mix @ image ** gamma)`` per pixel, clipped to [0, 1].

    Parameters
    ----------
    image : (..., 3) float, linear RGB in [0, 1] (values outside are clipped first, so
        that the power stays real).
    gamma : float > 0, the exponent applied to every channel.
    mix : (3, 3) float, output channel x input channel.
    gains : (3,) float, per output channel.

    Returns
    -------
    (..., 3) float32 in [0, 1].
    """
    if gamma <= 0:
        raise ValueError(f"gamma must be > 0, got {gamma}")
    mix = np.asarray(mix, np.float64).reshape(3, 3)
    gains = np.asarray(gains, np.float64).reshape(3)
    curved = np.power(np.clip(np.asarray(image, np.float64), 0.0, 1.0), gamma)
    out = (curved @ mix.T) * gains
    return np.clip(out, 0.0, 1.0).astype(np.float32)


def axial_heights(ref_depth: np.ndarray, camera: Camera) -> np.ndarray:
    """Height along the sensor's axis of the no-contact surface point each pixel sees.

    Parameters
    ----------
    ref_depth : (H, W) float, metres, no-contact planar z-depth.
    camera : Camera

    Returns
    -------
    (H, W) float64, metres: the camera-frame z of the back-projected point; NaN off the
    membrane (depth not finite or <= 0, or outside ``camera.mask``).
    """
    depth = np.asarray(ref_depth, np.float64)
    on = np.isfinite(depth) & (depth > 0) & camera.mask
    z = back_project(np.where(on, depth, 1.0), camera)[..., 2]
    return np.where(on, z, np.nan)


def fade_gain(z: np.ndarray, mu_per_m: float, z0_m: float) -> np.ndarray:
    """``exp(-mu * max(0, z - z0))``, 1 where z is NaN (off the membrane).

    z : (...) float, metres.  Returns the same shape, float64 in (0, 1].
    """
    z = np.asarray(z, np.float64)
    excess = np.maximum(0.0, np.nan_to_num(z - z0_m, nan=0.0))
    return np.exp(-mu_per_m * excess)


def falloff_gain(shape: tuple[int, int], axis_uv: tuple[float, float], f_px: float) -> np.ndarray:
    """cos^4 of each pixel ray's angle to an optical axis (natural vignetting).

    Parameters
    ----------
    shape : (H, W)
    axis_uv : (u, v) px, where the optical axis meets the image.
    f_px : float > 0, the lens' focal length in pixels.

    Returns
    -------
    (H, W) float64 in (0, 1], 1 at the axis: ``1 / (1 + (r / f)^2)^2`` with r the pixel's
    distance from the axis (cos^2 theta = 1 / (1 + tan^2 theta)).
    """
    if f_px <= 0:
        raise ValueError(f"f_px must be > 0, got {f_px}")
    v, u = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
    tan2 = ((u - axis_uv[0]) ** 2 + (v - axis_uv[1]) ** 2) / f_px**2
    return 1.0 / (1.0 + tan2) ** 2


def pillbox_kernel(radius_px: float, supersample: int = PILLBOX_SUPERSAMPLE) -> np.ndarray:
    """A uniform disc of ``radius_px`` pixels as a normalised kernel.

    Each weight is the share of its pixel's square the disc covers (``supersample`` x
    ``supersample`` sub-samples), so a small disc keeps its area pi r^2.

    Returns
    -------
    (2n + 1, 2n + 1) float32 summing to 1; ``[[1]]`` for a radius below one sub-sample.
    """
    if radius_px < 0:
        raise ValueError(f"radius_px must be >= 0, got {radius_px}")
    if radius_px < 1.0 / supersample:
        return np.ones((1, 1), np.float32)
    n = int(math.ceil(radius_px + 0.5))  # pixel k reaches |k| - 0.5 from the centre
    sub = (np.arange(supersample) + 0.5) / supersample - 0.5
    grid = (np.arange(-n, n + 1)[:, None] + sub[None, :]).ravel()  # sub-sample coordinates
    inside = (grid[:, None] ** 2 + grid[None, :] ** 2) <= radius_px**2
    cover = inside.reshape(2 * n + 1, supersample, 2 * n + 1, supersample).mean(axis=(1, 3))
    return (cover / cover.sum()).astype(np.float32)


def defocus_blur(image: np.ndarray, radius_px: float) -> np.ndarray:
    """Each channel convolved with a pillbox of ``radius_px`` (edges replicated).

    image : (H, W, C) or (H, W) float.  Returns the same shape, float32.
    """
    kernel = pillbox_kernel(radius_px)
    src = np.ascontiguousarray(image, dtype=np.float32)
    if kernel.shape == (1, 1):
        return src.copy()
    # The kernel is symmetric, so filter2D's correlation is the convolution.
    return cv2.filter2D(src, -1, kernel, borderType=cv2.BORDER_REPLICATE)


def seat_matrix(centre_uv: tuple[float, float], shift_px: tuple[float, float], rotation_deg: float) -> np.ndarray:
    """The (2, 3) affine map from a simulated pixel to where the seated camera sees it.

    The image turns by ``rotation_deg`` about ``centre_uv`` (positive: counter-clockwise
    as displayed, v down), then moves by ``shift_px`` = (du, dv):
    p' = R (p - c) + c + t.
    """
    a = math.radians(rotation_deg)
    c, s = math.cos(a), math.sin(a)
    rot = np.array([[c, s], [-s, c]])  # counter-clockwise on screen, where v points down
    centre = np.asarray(centre_uv, np.float64)
    t = centre - rot @ centre + np.asarray(shift_px, np.float64)
    return np.hstack([rot, t[:, None]])


def seat_warp(image: np.ndarray, centre_uv: tuple[float, float], shift_px: tuple[float, float],
              rotation_deg: float) -> np.ndarray:
    """The image as the off-centre, turned camera sees it (``seat_matrix``): bilinear,
    black where nothing maps.

    image : (H, W, C) or (H, W) float.  Returns the same shape, float32.
    """
    src = np.ascontiguousarray(image, dtype=np.float32)
    h, w = src.shape[:2]
    return cv2.warpAffine(src, seat_matrix(centre_uv, shift_px, rotation_deg), (w, h),
                          flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def division_maps(shape: tuple[int, int], centre_uv: tuple[float, float], f_px: float, lam: float
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Where each real pixel reads the simulated image under the division model.

    A real pixel at normalised radius r_d = |p - c| / f reads the simulated image at
    r_u = r_d / (1 + lam r_d^2), along the same direction from the centre.

    Returns
    -------
    (map_u, map_v) : (H, W) float32 each, px; -1 (outside, read as black) where
    1 + lam r_d^2 <= 0 (beyond a barrel's fold, where no simulated pixel maps).
    """
    if f_px <= 0:
        raise ValueError(f"f_px must be > 0, got {f_px}")
    v, u = np.mgrid[0 : shape[0], 0 : shape[1]].astype(np.float64)
    du, dv = (u - centre_uv[0]) / f_px, (v - centre_uv[1]) / f_px
    denominator = 1.0 + lam * (du**2 + dv**2)
    ok = denominator > 0
    scale = np.divide(1.0, denominator, out=np.zeros_like(denominator), where=ok)
    map_u = np.where(ok, centre_uv[0] + f_px * du * scale, -1.0)
    map_v = np.where(ok, centre_uv[1] + f_px * dv * scale, -1.0)
    return map_u.astype(np.float32), map_v.astype(np.float32)


def division_warp(image: np.ndarray, centre_uv: tuple[float, float], f_px: float, lam: float) -> np.ndarray:
    """The image through the division-model lens (``division_maps``): bilinear, black
    outside.

    image : (H, W, C) or (H, W) float.  Returns the same shape, float32.
    """
    src = np.ascontiguousarray(image, dtype=np.float32)
    map_u, map_v = division_maps(src.shape[:2], centre_uv, f_px, lam)
    return cv2.remap(src, map_u, map_v, interpolation=cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def softened_depth(depth: np.ndarray, ref_depth: np.ndarray, factor: float) -> np.ndarray:
    """The depth of a contact whose indentation a compliant membrane scales by ``factor``.

    Parameters
    ----------
    depth : (H, W) float, metres, the commanded contact's planar depth.
    ref_depth : (H, W) float, metres, the no-contact depth.
    factor : float >= 0, the share of the indentation kept.

    Returns
    -------
    (H, W) float, depth's dtype: ``ref - factor (ref - depth)`` where the indentation
    ``ref - depth`` is positive, ``depth`` elsewhere.
    """
    if factor < 0:
        raise ValueError(f"factor must be >= 0, got {factor}")
    d = np.asarray(depth, np.float64)
    r = np.asarray(ref_depth, np.float64)
    indentation = np.nan_to_num(r - d, nan=0.0)
    indented = indentation > 0
    out = np.where(indented, r - factor * indentation, d)
    return out.astype(np.asarray(depth).dtype if np.asarray(depth).dtype.kind == "f" else np.float64)


# --- The injector ---------------------------------------------------------------------------

class Described:
    """Applies the described mechanisms to plain simulated images of one sensor.

    Parameters
    ----------
    spec : SensorSpec
        The sensor; its camera gives the image size, focal length and image centre.
    ref_depth : (H, W) float
        Metres, the membrane's no-contact planar z-depth (``scenes.camera.reference_depth``).

    Attributes
    ----------
    camera : Camera
    ref_depth : (H, W) float64, metres.
    axial_z : (H, W) float64, metres, the no-contact surface's height along the axis
        (``axial_heights``), NaN off the membrane.
    centre_uv : (u, v) px, the image centre: the camera's principal point.
    """

    def __init__(self, spec: SensorSpec, ref_depth: np.ndarray):
        if not isinstance(spec, SensorSpec):
            raise ValueError(f"spec must be a SensorSpec, got {type(spec).__name__}")
        self.camera = Camera.from_spec(spec)
        if (not isinstance(ref_depth, np.ndarray) or ref_depth.shape != self.camera.shape
                or ref_depth.dtype.kind != "f"):
            got = f"{ref_depth.shape} {ref_depth.dtype}" if isinstance(ref_depth, np.ndarray) else type(ref_depth).__name__
            raise ValueError(f"ref_depth must be {self.camera.shape} float (metres), got {got}")
        self.ref_depth = ref_depth.astype(np.float64)
        self.axial_z = axial_heights(self.ref_depth, self.camera)
        if not np.isfinite(self.axial_z).any():
            raise ValueError("ref_depth has no finite, positive depth inside the camera's image circle")
        self.centre_uv = (float(self.camera.cx), float(self.camera.cy))

    def _check_image(self, image, name: str = "image") -> np.ndarray:
        shape = self.camera.shape + (3,)
        if not isinstance(image, np.ndarray) or image.shape != shape or image.dtype.kind != "f":
            got = f"{image.shape} {image.dtype}" if isinstance(image, np.ndarray) else type(image).__name__
            raise ValueError(f"{name} must be {shape} float linear RGB, got {got}")
        return image.astype(np.float32, copy=False)

    def apply(self, image: np.ndarray, mechanism: str, params: Mapping[str, float],
              depth: np.ndarray | None = None,
              render: Callable[[np.ndarray], np.ndarray] | None = None) -> np.ndarray:
        """The "real" image of one contact: its plain simulated image through a mechanism.

        Parameters
        ----------
        image : (H, W, 3) float32
            Linear RGB in [0, 1], the plain simulated image of the contact, the camera's size.
        mechanism : str
            One of ``MECHANISMS``.
        params : mapping
            Exactly ``PARAM_NAMES[mechanism]`` (``sample_params``).
        depth : (H, W) float, optional
            Metres, the contact's planar depth; needed by ``soft_membrane``.
        render : callable, optional
            depth (H, W) -> (H, W, 3) image, the plain simulator; needed by ``soft_membrane``.

        Returns
        -------
        (H, W, 3) float32 in [0, 1].
        """
        mechanism = _check_mechanism(mechanism)
        image = self._check_image(image)
        p = _check_params(mechanism, params)

        if mechanism == "gamma_mix_gains":
            gains = np.array([p[f"gain_{c}"] for c in _CHANNELS])
            out = camera_response(image, p["gamma"], mix_matrix(p), gains)
        elif mechanism == "axial_fade":
            out = image * fade_gain(self.axial_z, p["mu_per_m"], p["z0_m"])[..., None]
        elif mechanism == "lens_falloff":
            axis = (self.centre_uv[0] + p["axis_dx_px"], self.centre_uv[1] + p["axis_dy_px"])
            out = image * falloff_gain(self.camera.shape, axis, p["focal_scale"] * self.camera.f)[..., None]
        elif mechanism == "defocus":
            out = defocus_blur(image, p["radius_px"])
        elif mechanism == "seat_offset":
            out = seat_warp(image, self.centre_uv, (p["shift_x_px"], p["shift_y_px"]), p["rotation_deg"])
        elif mechanism == "barrel_lens":
            out = division_warp(image, self.centre_uv, self.camera.f, p["lambda"])
        else:  # soft_membrane
            if depth is None:
                raise ValueError("depth is required by soft_membrane: the contact's (H, W) planar depth, metres")
            if render is None or not callable(render):
                raise ValueError("render is required by soft_membrane: a callable depth -> (H, W, 3) image")
            depth = check_depth(depth, self.camera, "depth")
            out = self._check_image(np.asarray(render(softened_depth(depth, self.ref_depth, p["factor"]))),
                                    "render's image")
        return np.clip(out, 0.0, 1.0).astype(np.float32)
