"""Gap mechanisms written unlike the catalogue's formulas: the blind benchmark's second source.

``studies.gap.inject`` models each effect physically, but its formulas stay close to the
catalogue's (a power-law gamma, Beer-Lambert along the geodesic from each LED, a whole-
frame move of an injector-sized range). The catalogue must cover the general form of a
mechanism, not one formula of it, so the stratified benchmark also hides mechanisms
written here, in other functional forms, each standing for one catalogue effect
(``MECHANISMS``, the effect that should come first):

* ``colour_matrix_curve`` (camera_response): a general 3x3 colour matrix (rows need not
  sum to 1; off-diagonals of either sign) followed by a per-channel response curve of
  rational form, x (1 + c) / (1 + c x) (not a power law: its slope at 0 is finite), one
  that darkens (-1 < c < 0), as the case of issue 23.6 did (the injector's gamma and gains
  already brighten as often as they darken);
* ``fade_all_light`` (path_attenuation): every light that travels fades along the
  sensor, the background term included: the whole image times exp(-(z / L)^2), z the
  undeformed membrane's height above the LEDs' plane (not Beer-Lambert: the fade grows
  along the sensor, so the tip darkens far more than the body, as in issue 23.6, where
  the tip lost 0.27 and the body 0.03);
* ``frame_turn`` (misalignment): the whole frame turned by a few degrees about the
  frame's corner (pixel (0, 0), where ``scipy.ndimage.affine_transform`` turns an array
  without an offset; the catalogue turns about the image centre, so this is a turn about
  the centre plus a shift of about 20 px) and shifted by several pixels more, resampled
  by a cubic spline;
* ``frame_move`` (misalignment): the whole frame turned about its own centre and shifted,
  each drawn at random over the whole range a new user meets (a turn uniform within
  ``MOVE_TURN_DEG`` either way, a shift of uniform length up to ``MOVE_SHIFT_PX`` in a
  uniform direction), whatever the strength, resampled by the same cubic spline; on the
  real background and on a solid one.

Each mechanism acts on a finished image of the plain fast path (the simulated image the
diagnosis also gets), so ``apply`` is arrays in, arrays out. This module imports nothing
from ``studies.gap``: a benchmark that shared the catalogue's code would pass by
construction.
"""

from __future__ import annotations

import math
import numbers

import numpy as np
from scipy import ndimage

from scenes.camera import Camera, back_project, check_depth
from scenes.spec import SensorSpec

#: Each mechanism, the catalogue effect that should come first for it.
MECHANISMS = {"colour_matrix_curve": "camera_response", "fade_all_light": "path_attenuation",
              "frame_turn": "misalignment", "frame_move": "misalignment"}
#: The backgrounds each mechanism is benchmarked on (as the cases of issue 23.6 were; a
#: moved frame on the real no-contact capture and on a solid one, issue 74).
BACKGROUNDS = {"colour_matrix_curve": ("solid",), "fade_all_light": ("solid",), "frame_turn": ("real",),
               "frame_move": ("real", "solid")}

# Strength maps linearly from the first value (strength 0, weak but clearly visible) to
# the second (strength 1, strong) of each pair below.

#: colour_matrix_curve: bound of |off-diagonal| of the colour matrix, drawn uniformly in
#: [-this, this] per entry, -.
MATRIX_OFF_DIAGONAL = (0.08, 0.3)
#: colour_matrix_curve: bound of |log diagonal gain|, drawn per channel, -.
MATRIX_LOG_GAIN = (0.1, 0.35)
#: colour_matrix_curve: c of the response x (1 + c) / (1 + c x), a darkening curve; each
#: channel's c within 20% of this.
CURVE_BEND = (-0.25, -0.6)
#: fade_all_light: length L of the fade exp(-(z / L)^2) along the sensor's axis, m (the
#: GelTip's tip is 0.045 m above its LEDs).
FADE_LENGTH_M = (0.075, 0.035)
#: frame_turn: rotation of the frame about its corner, degrees (sign drawn).
TURN_ROTATION_DEG = (1.5, 4.5)
#: frame_turn: shift of the frame, px (direction drawn).
TURN_SHIFT_PX = (3.0, 9.0)
#: frame_move: the largest turn about the frame's centre, degrees, either way (drawn
#: uniformly within it at every strength).
MOVE_TURN_DEG = 4.0
#: frame_move: the longest shift, px (its length drawn uniformly up to it, at every strength).
MOVE_SHIFT_PX = 12.0


def _lerp(pair: tuple[float, float], strength: float) -> float:
    return float(pair[0] + (pair[1] - pair[0]) * strength)


def _check(mechanism, strength) -> tuple[str, float]:
    if mechanism not in MECHANISMS:
        raise ValueError(f"mechanism must be one of {tuple(MECHANISMS)}, got {mechanism!r}")
    if isinstance(strength, bool) or not isinstance(strength, numbers.Real) or not 0.0 <= strength <= 1.0:
        raise ValueError(f"strength must be a float in [0, 1], got {strength!r}")
    return mechanism, float(strength)


def sample_params(mechanism: str, strength: float, rng: np.random.Generator) -> dict[str, float]:
    """A mechanism's parameters at ``strength`` in [0, 1]; signs and directions from ``rng``.

    * colour_matrix_curve: ``m_<out><in>`` (the 3x3 matrix, rows r, g, b) and ``bend_<c>``
      (c of the curve per channel), -.
    * fade_all_light: ``length_m``, m.
    * frame_turn: ``rotation_rad`` (counter-clockwise as displayed) about the pivot
      (``pivot_x_px``, ``pivot_y_px``) = (0, 0), then ``shift_x_px``, ``shift_y_px``.
    * frame_move: ``rotation_rad`` about the frame's centre, then ``shift_x_px``,
      ``shift_y_px``: random draws over the whole range (``MOVE_TURN_DEG``,
      ``MOVE_SHIFT_PX``), which ``strength`` does not narrow.
    """
    mechanism, s = _check(mechanism, strength)
    if mechanism == "colour_matrix_curve":
        params = {}
        off, log_gain = _lerp(MATRIX_OFF_DIAGONAL, s), _lerp(MATRIX_LOG_GAIN, s)
        for i, row in enumerate("rgb"):
            for j, col in enumerate("rgb"):
                params[f"m_{row}{col}"] = (math.exp(float(rng.uniform(-log_gain, log_gain))) if i == j
                                           else float(rng.uniform(-off, off)))
        for c in "rgb":
            params[f"bend_{c}"] = _lerp(CURVE_BEND, s) * float(rng.uniform(0.8, 1.2))
        return params
    if mechanism == "fade_all_light":
        return {"length_m": _lerp(FADE_LENGTH_M, s)}
    direction = float(rng.uniform(0.0, 2.0 * math.pi))
    if mechanism == "frame_move":
        shift = float(rng.uniform(0.0, MOVE_SHIFT_PX))
        return {"rotation_rad": math.radians(float(rng.uniform(-MOVE_TURN_DEG, MOVE_TURN_DEG))),
                "shift_x_px": shift * math.cos(direction), "shift_y_px": shift * math.sin(direction)}
    shift = _lerp(TURN_SHIFT_PX, s)
    return {"rotation_rad": (1.0 if rng.random() < 0.5 else -1.0) * math.radians(_lerp(TURN_ROTATION_DEG, s)),
            "shift_x_px": shift * math.cos(direction), "shift_y_px": shift * math.sin(direction),
            "pivot_x_px": 0.0, "pivot_y_px": 0.0}


# --- the mechanisms, arrays in and out -------------------------------------------------------


def matrix_curve(image: np.ndarray, matrix: np.ndarray, bend) -> np.ndarray:
    """A camera whose colour matrix and response curve are unlike a gamma.

    out_c = y_c (1 + b_c) / (1 + b_c y_c), y = clip(matrix @ in, 0, 1): a rational
    (Reinhard-like) curve through 0 and 1, brighter for b_c > 0, darker for -1 < b_c < 0.

    image : (..., 3) float linear RGB in [0, 1]; matrix : (3, 3), out = matrix @ in;
    bend : (3,) b_c, each > -1.  Returns image's shape and dtype.
    """
    bend = np.asarray(bend, dtype=np.float64)
    if bend.shape != (3,) or not np.all(bend > -1.0):
        raise ValueError(f"bend must be 3 values > -1, got {bend}")
    y = np.clip(np.asarray(image, np.float64) @ np.asarray(matrix, np.float64).T, 0.0, 1.0)
    return (y * (1.0 + bend) / (1.0 + bend * y)).astype(image.dtype)


def axial_height(ref_depth: np.ndarray, camera: Camera, spec: SensorSpec) -> np.ndarray:
    """(H, W) float32 metres: the undeformed membrane's height along the sensor's axis
    (the camera's z) above the plane of the LEDs, >= 0; 0 off the image circle."""
    ref_depth = check_depth(ref_depth, camera, "ref_depth")
    z = back_project(np.asarray(ref_depth, np.float64), camera)[..., 2]
    plane = float(np.mean([led.position[2] for led in spec.leds]))
    return (np.maximum(z - plane, 0.0) * camera.mask).astype(np.float32)


def axial_fade(image: np.ndarray, height_m: np.ndarray, length_m: float) -> np.ndarray:
    """Every light fading along the sensor: image exp(-(z / L)^2), the background included.

    image : (H, W, 3) float; height_m : (H, W) z, metres (``axial_height``); length_m : L,
    metres, > 0.  Returns image's shape and dtype.
    """
    if not length_m > 0:
        raise ValueError(f"length_m must be > 0 m, got {length_m}")
    fade = np.exp(-np.square(np.asarray(height_m, np.float64) / length_m))
    return (image * fade[..., None]).astype(image.dtype)


def turn_frame(image: np.ndarray, rotation_rad: float, shift_x_px: float, shift_y_px: float,
               centre: tuple[float, float]) -> np.ndarray:
    """The whole frame turned by ``rotation_rad`` (counter-clockwise as displayed) about
    ``centre`` (u, v) px, then shifted by (shift_x_px, shift_y_px) px; black where nothing
    maps. Cubic-spline resampling (``scipy.ndimage.affine_transform``, order 3), clipped
    to the range of the input and the black fill.

    image : (H, W, 3) float.  Returns the same shape and dtype.
    """
    # Output pixel q (row, col) shows input p = R^-1 (q - c - t) + c; displayed
    # counter-clockwise is clockwise in (row, col) with rows pointing down.
    c, s = math.cos(rotation_rad), math.sin(rotation_rad)
    inverse = np.array([[c, s], [-s, c]])  # R^-1 in (row, col) for the displayed turn
    centre_rc = np.array([centre[1], centre[0]], float)
    t = np.array([shift_y_px, shift_x_px], float)
    offset = centre_rc - inverse @ (centre_rc + t)
    out = np.empty_like(image)
    for ch in range(image.shape[-1]):
        out[..., ch] = ndimage.affine_transform(np.asarray(image[..., ch], np.float64), inverse, offset, order=3,
                                                mode="constant", cval=0.0)
    return np.clip(out, min(float(image.min()), 0.0), max(float(image.max()), 0.0))  # the spline's overshoot


class Unlike:
    """The mechanisms for one sensor: what they need that does not depend on the image.

    spec : the sensor; ref_depth : (H, W) float metres, its no-contact depth D_ref.
    """

    def __init__(self, spec: SensorSpec, ref_depth: np.ndarray):
        self.spec = spec
        self.camera = Camera.from_spec(spec)
        self.height = axial_height(ref_depth, self.camera, spec)

    def apply(self, image: np.ndarray, mechanism: str, params: dict[str, float]) -> np.ndarray:
        """(H, W, 3) float image with ``mechanism`` at ``params`` (``sample_params``)."""
        _check(mechanism, 0.0)
        if mechanism == "colour_matrix_curve":
            matrix = np.array([[params[f"m_{r}{c}"] for c in "rgb"] for r in "rgb"])
            return matrix_curve(image, matrix, [params[f"bend_{c}"] for c in "rgb"])
        if mechanism == "fade_all_light":
            return axial_fade(image, self.height, params["length_m"])
        if mechanism == "frame_move":
            h, w = image.shape[:2]
            pivot = ((w - 1) / 2.0, (h - 1) / 2.0)
        else:
            pivot = (params["pivot_x_px"], params["pivot_y_px"])
        return turn_frame(image, params["rotation_rad"], params["shift_x_px"], params["shift_y_px"], pivot)
