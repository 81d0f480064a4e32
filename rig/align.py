"""Align the simulator's images with a real camera's, from the no-contact image.

The transform is :class:`scenes.profile.Alignment` (rotation, scale and shift of the
membrane's image about the spec camera's principal point; ``scenes.profile.align_image``
maps a simulated image into the real camera's frame). A capture's comes from one of two
places (:func:`capture_alignment`):

- a calibrated unit's profile (``tactile-sim calibrate``), used as it is;
- else :func:`estimate_alignment`, a registration of the simulated no-contact image onto
  the real one.

The registration is direct image alignment (Lucas and Kanade 1981; Baker and Matthews
2004, "Lucas-Kanade 20 years on"): Gauss-Newton (``scipy.optimize.least_squares``) on the
four parameters, the residual being the real image less the simulated one sampled as
``align_image`` samples it, under a colour map solved in closed form at every step
(variable projection), so that brightness and colour balance, which differ between a real
camera and the simulator, do not bias the geometry (ECC, Evangelidis and Psarakis 2008,
is invariant to one gain and offset in the same way). Two colour maps, because the LEDs'
colours are what shows a turn:

- a gain and offset per channel: the turn of the shading's pattern shows as a change of
  colour at each place, so the turn is fitted under this map;
- any affine map of RGB: it can mix the three LEDs' images, so it follows a turn (a turned
  smooth lobe is nearly a mix of the three) and cannot fix one, but a colour cross-talk
  that the per-channel map cannot follow no longer biases the shift and scale (on the
  test's cross-talk, 1 px of shift under the per-channel map alone).

So each level of a coarse-to-fine pyramid of block means (``scenes.images.block_mean``)
fits all four under the per-channel map, from the identity; the finest then refits scale
and shift under the affine map and the turn alone under the per-channel map. Pixels are
compared well inside the real image's lit region and the moved simulation's (the lens'
circle does not move with the membrane, so its edge must not pull the fit), and a real
channel that is clipped is left out (it says only "at least 1").

Why not a library's registration: scikit-image registers translations
(``phase_cross_correlation``) and dense flow, not a similarity of smooth images; log-polar
phase correlation needs the translation first, and the fixed circle's edge dominates the
spectra of these low-texture images; OpenCV's ``findTransformECC`` has no similarity
motion, takes one grey channel (so one gain, where the LEDs' colours differ per channel)
and is an optional extra. Fitting through ``Alignment.sampling`` also keeps the
renderers' convention by construction.

What one no-contact image can tell: the place and size of the shading's structure, and
the turn of its pattern, which is the LED ring's turn as much as the membrane's (the
membrane is nearly symmetric about its axis); ``tactile-sim calibrate`` separates them
with taps. Against a simulation that is far from the real image (an uncalibrated sensor),
the registration finds the best of a poor match: check ``residual_after`` against
``residual_before``.
"""

from __future__ import annotations

import math
from dataclasses import asdict, replace

import numpy as np

from scenes.camera import Camera
from scenes.profile import Alignment, Profile, align_image
from scenes.spec import SensorSpec

#: The ``method`` of an alignment block: a calibration's alignment, or a registration.
METHODS = ("profile", "registration")
#: Pixels nearer than this share of the image's height to the edge of the real image's
#: lit region or of the moved simulation's are not compared: the lens' circle, which does
#: not move with the membrane, must not pull the fit, and the simulation's edge moves
#: within a level's fit.
EDGE_MARGIN = 0.04
#: A channel at or above this value is clipped (8-bit 254.5) and is not compared ...
CLIP_LEVEL = 254.5 / 255
#: ... nor is a channel this near (pixels) a clipped one, whose noise the clipping cut.
CLIP_MARGIN_PX = 2
#: The pyramid's coarsest level has at least this many rows ...
COARSEST_ROWS = 60
#: ... and its finest at most this many: on the tests' synthetic images, fits at 240 rows
#: are within 0.05 px of the truth, so finer levels would cost four times as much for nothing.
FINEST_ROWS = 240
#: Each level's fits, (colour map, parameters fitted): q = (rotation, log scale, shift u,
#: shift v) with the first two times the image circle's radius (pixels at the circle).
COARSE_STAGES = (("channel", [0, 1, 2, 3]),)
FINEST_STAGES = (("channel", [0, 1, 2, 3]), ("full", [1, 2, 3]), ("channel", [0]))
#: The scales searched (``Alignment`` allows [0.5, 2]; a membrane that far off is not one sensor).
SCALE_BOUNDS = (0.7, 1.4)
#: The shifts searched, a share of the image's height either way.
SHIFT_BOUND = 0.25
#: Forward-difference step of the Jacobian, pixels of the working level: bilinear sampling
#: makes the residual piecewise linear between pixels, so the step spans a good part of one.
DIFF_STEP_PX = 0.3
#: A fit stops when a step moves q by less than XTOL of its norm, or lowers the cost by
#: less than FTOL of it ...
XTOL = 1e-3
FTOL = 1e-4
#: ... or after this many steps.
MAX_STEPS = 100
#: A tiny ridge on the colour map's normal equations (a flat channel leaves them singular).
RIDGE = 1e-9
#: Fewer compared pixels than this cannot fix four parameters and a colour map: at the
#: finest level from the start a ValueError, at a coarse level the level is skipped.
MIN_PIXELS = 200


def estimate_alignment(real_background: np.ndarray, sim_background: np.ndarray, camera: Camera, *,
                       mask: np.ndarray | None = None) -> tuple[Alignment, dict]:
    """Register the simulated no-contact image onto the real one (see the module doc).

    Parameters
    ----------
    real_background : (h, w, 3) float in [0, 1], the real camera's no-contact image.
    sim_background : (h, w, 3) float in [0, 1], the simulator's no-contact image of the
        spec's camera (black outside its image circle, or not cut at all).
    camera : the spec's camera at its full resolution (``Camera.from_spec(spec)``); the
        images are that camera's frame at any whole scale (h / height == w / width).
    mask : (h, w) bool, the real image's pixels that may be compared (e.g. leaving out a
        scratch or a mark); it is narrowed further to well inside both images' lit
        regions and unclipped channels. None: all of them.

    Returns
    -------
    alignment : ``Alignment`` (rotation_rad, scale, shift_px in the full camera's pixels;
        no LED azimuths) that ``align_image(sim_background, alignment, camera)`` maps onto
        the real image.
    info : dict, JSON-ready: ``method`` "registration"; ``residual_before`` and
        ``residual_after``, the RMS of the real image less the simulated one under its
        per-channel gain and offset, over the last level's compared pixels and unclipped
        channels, before (identity) and after; ``pixels`` compared there;
        ``levels``, the rows of each level fitted; ``evaluations`` of the residual;
        ``converged``, False when a fit of the finest level stopped on its step limit or
        on a bound of the search (``SCALE_BOUNDS``, ``SHIFT_BOUND``).
    """
    real = _check_image(real_background, "real_background")
    sim = _check_image(sim_background, "sim_background")
    if real.shape != sim.shape:
        raise ValueError(f"real_background is {real.shape} but sim_background is {sim.shape}: render the "
                         "simulation at the real image's size")
    h, w = real.shape[:2]
    if h * camera.width != w * camera.height:
        raise ValueError(f"the images are {w}x{h} px but the spec's camera is {camera.width}x{camera.height}: "
                         "expected the camera's frame at a whole scale (resize the capture, e.g. open_camera(size=...))")
    if mask is not None:
        mask = np.asarray(mask)
        if mask.shape != (h, w) or mask.dtype != bool:
            raise ValueError(f"mask must be ({h}, {w}) bool, got {mask.shape} {mask.dtype}")
    radius = camera.mask_radius_px
    unit = np.array([1.0 / radius, 1.0 / radius, 1.0, 1.0])  # q -> (rad, log scale, px, px)
    bound = SHIFT_BOUND * camera.height
    lower = np.array([-np.inf, math.log(SCALE_BOUNDS[0]) * radius, -bound, -bound])
    upper = np.array([np.inf, math.log(SCALE_BOUNDS[1]) * radius, bound, bound])
    maps = _Maps(real, sim, mask, camera, unit)
    factors = _pyramid(h, w)
    q = np.zeros(4)
    compare, _ = maps.compared(factors[-1], q)
    if compare.sum() < MIN_PIXELS:
        raise ValueError(f"only {int(compare.sum())} pixels (at {h // factors[-1]} rows) lie well inside both images' "
                         f"non-black regions with an unclipped channel{' and in mask' if mask is not None else ''}; "
                         f"expected at least {MIN_PIXELS}: are the images black or saturated?")
    evaluations, converged, levels = 0, False, []
    for factor in factors:
        compare, valid = maps.compared(factor, q)
        if compare.sum() < MIN_PIXELS:
            continue  # too few pixels at this level to fit on (at the finest: moved out, not converged)
        r, s = maps.level(factor)
        step = DIFF_STEP_PX * camera.height / r.shape[0]  # in the full camera's pixels
        finest = factor == factors[-1]
        converged = finest
        for colour, free in FINEST_STAGES if finest else COARSE_STAGES:
            residual = _residual_function(r, s, compare, valid, camera, unit, colour)
            q, solution, count = _least_squares(residual, q, free, step, lower, upper)
            evaluations += count
            converged = converged and solution.status > 0 and not np.any(solution.active_mask)
        levels.append(r.shape[0])
        fitted = r, s, compare, valid
    residual = _residual_function(*fitted, camera, unit, "channel")
    alignment = _to_alignment(q, unit)
    info = {"method": "registration", "residual_before": _rms(residual(np.zeros(4))),
            "residual_after": _rms(residual(q)), "pixels": int(fitted[2].sum()), "levels": levels,
            "evaluations": int(evaluations), "converged": bool(converged)}
    return replace(alignment, rotation_rad=math.remainder(alignment.rotation_rad, 2 * math.pi)), info


def capture_alignment(real_background: np.ndarray, spec: SensorSpec, *, profile: Profile | None = None,
                      sim_background: np.ndarray | None = None) -> dict:
    """The ``alignment`` block of a capture's dataset.json (JSON-ready).

    Parameters
    ----------
    real_background : (h, w, 3) float in [0, 1], the capture's no-contact image.
    spec : the sensor's spec (its camera is the frame of the alignment).
    profile : a calibrated unit's profile (checked against ``spec``): its alignment is
        used as it is, ``{"method": "profile", "rotation_rad", "scale", "shift_px",
        "led_azimuth_rad"}``.
    sim_background : (h, w, 3) float in [0, 1], the simulator's no-contact image, needed
        without a profile: ``{"method": "registration", "rotation_rad", "scale",
        "shift_px", "residual_before", "residual_after", "converged"}`` from
        :func:`estimate_alignment`.

    Read it back with :func:`alignment_from_dict`.
    """
    _check_image(real_background, "real_background")
    if profile is not None and sim_background is not None:
        raise ValueError("pass profile or sim_background, not both: with a profile its calibrated alignment is "
                         "used as it is, and no registration runs")
    if profile is not None:
        profile.check(spec)
        return {"method": "profile", **_plain(asdict(profile.alignment))}
    if sim_background is None:
        raise ValueError("sim_background is required without a profile: the alignment is registered from the "
                         "simulated no-contact image (render it at the capture's size), or pass the unit's profile")
    alignment, info = estimate_alignment(real_background, sim_background, Camera.from_spec(spec))
    block = {"method": "registration", **_plain(asdict(alignment))}
    del block["led_azimuth_rad"]  # a no-contact registration does not give them
    block.update({key: info[key] for key in ("residual_before", "residual_after", "converged")})
    return block


def alignment_from_dict(block: dict) -> Alignment:
    """The ``Alignment`` of an alignment block (:func:`capture_alignment`); a ValueError
    naming the key that is missing or wrong. Keys other than the transform's (residuals)
    are reports and are not read."""
    if not isinstance(block, dict):
        raise ValueError(f"alignment block must be a dict, got {type(block).__name__}")
    method = block.get("method")
    if method not in METHODS:
        raise ValueError(f"alignment block 'method' must be one of {list(METHODS)}, got {method!r}")
    expected = {"rotation_rad": 1, "scale": 1, "shift_px": 2}
    values = {}
    for key, n in expected.items():
        if key not in block:
            raise ValueError(f"alignment block ({method}) has no {key!r}; expected keys {['method', *expected]}")
        values[key] = _numbers(block[key], n, key)
    turns = _numbers(block.get("led_azimuth_rad", []), None, "led_azimuth_rad")
    try:
        return Alignment(rotation_rad=values["rotation_rad"][0], scale=values["scale"][0],
                         shift_px=tuple(values["shift_px"]), led_azimuth_rad=tuple(turns))
    except ValueError as exc:
        raise ValueError(f"alignment block: {exc}") from None


def _check_image(image, name: str) -> np.ndarray:
    """(h, w, 3) float in [0, 1], finite -> float64; else a ValueError naming it."""
    if not isinstance(image, np.ndarray) or image.ndim != 3 or image.shape[2] != 3 or image.dtype.kind != "f":
        got = f"{image.shape} {image.dtype}" if isinstance(image, np.ndarray) else type(image).__name__
        raise ValueError(f"{name} must be (h, w, 3) float RGB in [0, 1], got {got}")
    bad = ~np.isfinite(image)
    if bad.any():
        raise ValueError(f"{name} has {int(bad.sum())} NaN or infinite values; expected finite RGB in [0, 1]")
    if image.min() < 0 or image.max() > 1:
        raise ValueError(f"{name} must be in [0, 1], got values in [{image.min():g}, {image.max():g}]")
    return image.astype(np.float64)


def _pyramid(h: int, w: int) -> list[int]:
    """Block sizes, coarse to fine: the finest the smallest whole divisor of the image that
    gives at most ``FINEST_ROWS`` rows, then doubling while the blocks divide the image
    and leave at least ``COARSEST_ROWS`` rows."""
    factor = 1
    while h // factor > FINEST_ROWS and h % (2 * factor) == 0 and w % (2 * factor) == 0:
        factor *= 2
    factors = [factor]
    while h % (2 * factors[-1]) == 0 and w % (2 * factors[-1]) == 0 and h // (2 * factors[-1]) >= COARSEST_ROWS:
        factors.append(2 * factors[-1])
    return factors[::-1]


class _Maps:
    """The images and their masks at full size, and at each level of the pyramid."""

    def __init__(self, real: np.ndarray, sim: np.ndarray, mask: np.ndarray | None, camera: Camera, unit: np.ndarray):
        from scipy import ndimage

        self.real, self.sim, self.camera, self.unit = real, sim, camera, unit
        self.real_lit, self.sim_lit = real.any(axis=-1), sim.any(axis=-1)
        # A clipped channel says only "at least 1", and its neighbours' noise was cut.
        clipped = real >= CLIP_LEVEL
        self.clipped = np.stack([ndimage.binary_dilation(clipped[..., c], iterations=CLIP_MARGIN_PX)
                                 for c in range(3)], axis=-1)
        self.keep = np.ones(real.shape[:2], bool) if mask is None else mask

    def level(self, factor: int) -> tuple[np.ndarray, np.ndarray]:
        """The real and simulated images in blocks of ``factor``."""
        from scenes.images import block_mean

        return (block_mean(self.real, factor), block_mean(self.sim, factor)) if factor > 1 else (self.real, self.sim)

    def compared(self, factor: int, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """At blocks of ``factor`` with the simulation moved by q: (h, w) bool, the pixels
        compared (inside the real image's lit region and the moved simulation's by
        ``EDGE_MARGIN`` of the height, in the mask, a channel unclipped), and (K, 3) bool,
        their unclipped channels. A block is lit and kept only if all its pixels are, and
        clipped if any is."""
        from scipy import ndimage

        from scenes.images import block_mean

        def blocks(image):
            return block_mean(image.astype(np.float64), factor)

        real_lit, sim_lit, keep = (blocks(x) == 1.0 for x in (self.real_lit, self.sim_lit, self.keep))
        clipped = blocks(self.clipped) > 0
        moved_lit = align_image(sim_lit.astype(np.float64), _to_alignment(q, self.unit), self.camera) > 1 - 1e-6
        margin = max(1, int(round(EDGE_MARGIN * real_lit.shape[0])))
        compare = ndimage.binary_erosion(real_lit & moved_lit, iterations=margin, border_value=0)
        compare &= keep & ~clipped.all(axis=-1)
        return compare, ~clipped[compare]


def _residual_function(real: np.ndarray, sim: np.ndarray, compare: np.ndarray, valid: np.ndarray, camera: Camera,
                       unit: np.ndarray, colour: str):
    """q -> the residuals of the ``compare`` pixels' ``valid`` channels: the real image less the
    simulated one moved by q (sampled as ``align_image`` samples) under its best colour map,
    ``colour``: "full" (each real channel an affine function of the three simulated ones)
    or "channel" (a gain and offset per channel)."""
    from scipy import ndimage

    target = real[compare]  # (K, 3)
    channels = np.ascontiguousarray(sim.transpose(2, 0, 1))
    ones = np.ones((len(target), 1))

    def residual(q: np.ndarray) -> np.ndarray:
        coords = _to_alignment(q, unit).sampling(sim.shape[:2], camera)[:, compare]
        moved = np.stack([ndimage.map_coordinates(c, coords, order=1, mode="constant") for c in channels], -1)
        out = []
        for c in range(3):  # the colour map, by its normal equations (a few well-scaled columns)
            k = valid[:, c]
            design = np.concatenate([moved[k] if colour == "full" else moved[k, c:c + 1], ones[k]], axis=-1)
            normal = design.T @ design + RIDGE * np.eye(design.shape[1])
            out.append(target[k, c] - design @ np.linalg.solve(normal, design.T @ target[k, c]))
        return np.concatenate(out)

    return residual


def _least_squares(residual, q0: np.ndarray, free: list[int], step: float, lower: np.ndarray, upper: np.ndarray):
    """scipy's least_squares over the ``free`` parameters of q0 (the others held) within
    the bounds, with a forward-difference Jacobian of step ``step``: (q, the solution, the
    number of residual evaluations)."""
    from scipy import optimize

    count, last = [0], {}

    def at(x):
        key = x.tobytes()
        if key not in last:  # least_squares asks for the Jacobian where it has the residual
            q = q0.copy()
            q[free] = np.clip(x, lower[free], upper[free])  # a Jacobian's step may poke past a bound
            count[0] += 1
            last.clear()
            last[key] = residual(q)
        return last[key]

    def jacobian(x):
        f = at(x)
        columns = []
        for i in range(x.size):
            e = np.zeros_like(x)
            e[i] = step
            columns.append((at(x + e) - f) / step)
        at(x)
        return np.stack(columns, axis=-1)

    solution = optimize.least_squares(at, q0[free], jac=jacobian, bounds=(lower[free], upper[free]),
                                      xtol=XTOL, ftol=FTOL, max_nfev=MAX_STEPS)
    q = q0.copy()
    q[free] = solution.x
    return q, solution, count[0]


def _rms(residual: np.ndarray) -> float:
    return float(np.sqrt(np.mean(residual**2)))


def _to_alignment(q: np.ndarray, unit: np.ndarray) -> Alignment:
    """The Alignment of q (rotation and log scale times the circle's radius, shift px)."""
    rotation, log_scale, u, v = q * unit
    return Alignment(rotation_rad=float(rotation), scale=float(math.exp(log_scale)), shift_px=(float(u), float(v)))


def _numbers(value, n: int | None, key: str) -> list[float]:
    """``value`` as n finite numbers (a scalar when n is 1; any count when n is None)."""
    items = [value] if n == 1 and not isinstance(value, (list, tuple)) else value
    ok = isinstance(items, (list, tuple)) and (n is None or len(items) == n) and all(
        isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in items)
    if not ok:
        count = "a list of" if n is None else ("one" if n == 1 else f"{n}")
        raise ValueError(f"alignment block {key!r} must be {count} finite number{'s' if n != 1 else ''}, got {value!r}")
    return [float(v) for v in items]


def _plain(value):
    """Tuples -> lists, recursively (JSON-ready); unset (None) entries left out."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items() if v is not None}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value
