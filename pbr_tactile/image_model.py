"""The image model of a real sensor built from the reference's basis images (its fit:
``pbr_tactile.image_fit``).

The reference renders one grey basis image per source once (``pbr_tactile.basis``: each
LED, or each LED group, and its leak into the glass core, per unit flux) and a real image
is modelled as

    I_c(p) = clip((V(p) sum_s g_sc A_s(T_m(s)^-1 p) + o_c) ** (1 / gamma), 0, sat_c)

- A_s : source s's basis image, rendered with the physical effects (absorption,
  scattering, coating albedo) of one point of a coarse grid; common random numbers (one
  seed) across the grid, so differences between grid points are not noise;
- T_m : the membrane's alignment for the source's LED m: a rotation about the optical
  axis by theta + phi_m (the global rotation and each LED's azimuth offset, which the
  rotationally symmetric membrane turns into an image rotation), and the real camera
  against the one the basis was rendered with (``scenes.profile.Alignment``): the spec's
  focal length times a scale, its principal point shifted, the lens' own k1 (each pixel
  reads the basis where its ray lands; a no-contact basis is rendered wider than the
  spec's camera, ``basis.basis_camera``); the image circle is the lens' and does not move. Where m is an LED group, A_s is its
  source at the arc's centre summed over the group's LEDs, each turned by its place along
  the arc, span_m times its offset (``scenes.spec.LEDGroup.offsets``), so each group's
  centre (phi_m) and span are fitted;
- g_sc >= 0 : each source's gain in each channel, the product of its power, its spectrum
  under the camera's filters and the white balance, which one image cannot separate: they
  are fitted together, by non-negative least squares, for every value of the nonlinear
  parameters (variable projection), and the core leak fraction is read from them. With
  the sources' film responses R (``ImageModel(response=)``: each LED's spectrum under the
  camera's filters, ``pbr_tactile.render.source_response``) the gains are not a free mix
  but g_mc = p_m R_mc w_c: one power p_m per LED and one white balance w_c per channel,
  so each LED's light reaches the channels only as its spectrum does
  (``solve_spectral_gains``);
- V : the lens' relative illumination 1 + a1 r^2 + a2 r^4, non-increasing and positive;
- gamma, o_c, sat_c : the camera's response, black offset and clip level. Clipped real
  pixels are censored: a prediction above the clip level there costs nothing.

The nonlinear parameters (theta, phi_m, the leaks, scale, shift, a1, a2, gamma, the
groups' spans and k1) are searched by bounded least squares from several rotations
(``pbr_tactile.image_fit.ImageFitter``); the physical ones on the calibration's grid.

Where the real camera is known to be the spec's (``ImageModel(known_alignment=True)``: a
unit whose spec was written from its own camera's record, as the public GelSight's), the
membrane's alignment is held there: theta 0, scale 1, no shift, the spec's k1, searched
from one start. Then only the LEDs' own azimuths (within AZIMUTH_BOUND_RAD of the spec's),
leaks, fall-off, response and gains are fitted. Why: with three LEDs 120 deg apart and a
free gain per LED and channel, a turn of a third of the circle that swaps the LEDs'
colours costs a no-contact image almost nothing. On the GelSight's presses the free
search took it (2.19 rad) and left the taps' held-out change R^2 negative; held at the
camera, it was 0.50 / 0.17 / 0.44.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage, optimize

from scenes.camera import Camera
from scenes.profile import Alignment, CameraProfile, camera_response, circle_radius, relative_illumination

from .basis import is_leak, led_of_source
from .real_image import CLIP_LEVEL

#: Bounds of the fit: LED azimuth offsets (rad) from the spec's, scale, shift (px at the
#: camera's resolution), response exponent.
AZIMUTH_BOUND_RAD = math.radians(25.0)
SCALE_BOUNDS = (0.8, 1.25)
SHIFT_BOUND_PX = 40.0
#: The real lens' k1 (scenes.camera.lens_radius), where the fit searches it.
K1_BOUNDS = (-0.5, 0.5)
GAMMA_BOUNDS = (0.5, 3.0)
#: A webcam's response, where the fit holds the camera to one (``ImageModel(webcam=True)``):
#: its encoding's exponent (sRGB's 2.2, give or take 0.4) and its black level, the image
#: value of no light, at most this. Free, the exponent and offsets also shape how evenly
#: the frame is lit: on the public GelSight's frame, LEDs laid out under the plate were
#: fitted at an exponent of 0.5 to 0.6 with offsets of 0.45 to 0.64, a camera that sees
#: a third of its level without light (docs/results/real-gelsight.md).
WEBCAM_GAMMA = (1.8, 2.6)
WEBCAM_BLACK = 0.1
#: The lens' fall-off V = 1 + a1 r^2 + a2 r^4 is searched as V(1) = 1 + a1 + a2 in
#: [MIN_EDGE_ILLUMINATION, 1] and the r^4 share a2 / (a1 + a2) in [0, 1]: every value
#: searched is a lens a profile accepts (non-increasing, positive).
MIN_EDGE_ILLUMINATION = 0.02
#: Arc images (an LED group's source summed along its arc) kept per model.
ARC_CACHE = 256


@dataclass(frozen=True)
class Nonlinear:
    """The nonlinear parameters (see the module doc); lengths in camera pixels. ``leak``
    is each LED's fraction of power emitted into the glass core."""

    rotation_rad: float
    led_azimuth_rad: tuple[float, ...]
    leak: tuple[float, ...]
    scale: float
    shift_px: tuple[float, float]
    vignetting: tuple[float, float]
    gamma: float
    #: each unit's arc span, rad, where the basis' units are LED groups (ImageModel.arcs)
    span_rad: tuple[float, ...] = ()
    #: the real lens' first radial distortion coefficient (scenes.camera.lens_radius; its
    #: k2 is the spec's)
    k1: float = 0.0

    def vector(self) -> np.ndarray:
        """The searched coordinates: the scale as its log, the fall-off as V(1) and its
        r^4 share (see MIN_EDGE_ILLUMINATION), then the spans."""
        total = -sum(self.vignetting)
        quartic = -self.vignetting[1] / total if total > 0 else 0.0
        return np.r_[self.rotation_rad, self.led_azimuth_rad, self.leak, math.log(self.scale), self.shift_px,
                     1.0 - total, quartic, self.gamma, self.span_rad, self.k1]

    def names(self) -> list[str]:
        """The searched coordinates' names, in ``vector``'s order."""
        n = len(self.led_azimuth_rad)
        return (["rotation_rad"] + [f"led_azimuth_rad[{i}]" for i in range(n)] + [f"leak[{i}]" for i in range(n)]
                + ["log_scale", "shift_u", "shift_v", "edge_illumination", "quartic_share", "gamma"]
                + [f"span_rad[{i}]" for i in range(len(self.span_rad))] + ["k1"])

    @classmethod
    def from_vector(cls, z: np.ndarray, leds: int, arcs: bool = False) -> Nonlinear:
        """``leds`` units; ``arcs``: the vector ends with their spans."""
        z = np.asarray(z, np.float64)
        n = leds
        total, quartic = 1.0 - float(z[4 + 2 * n]), float(z[5 + 2 * n])
        return cls(float(z[0]), tuple(map(float, z[1:1 + n])), tuple(map(float, z[1 + n:1 + 2 * n])),
                   float(math.exp(z[1 + 2 * n])), (float(z[2 + 2 * n]), float(z[3 + 2 * n])),
                   (-total * (1.0 - quartic), -total * quartic), float(z[6 + 2 * n]),
                   tuple(map(float, z[7 + 2 * n:7 + 3 * n])) if arcs else (), float(z[-1]))

    def tied(self) -> Nonlinear:
        """The same image with the LED azimuth offsets' mean moved into the rotation,
        which is then wrapped to (-pi, pi]: one no-contact image sees only their sums,
        and this is the tie the profile reports (see NOT_IDENTIFIABLE)."""
        mean = float(np.mean(self.led_azimuth_rad)) if self.led_azimuth_rad else 0.0
        rotation = math.remainder(self.rotation_rad + mean, 2 * math.pi)
        return dataclasses.replace(self, rotation_rad=rotation,
                                   led_azimuth_rad=tuple(a - mean for a in self.led_azimuth_rad))

    @classmethod
    def start(cls, leds: int, rotation_rad: float = 0.0, leak: float = 0.0, span_rad: tuple = (),
              k1: float = 0.0) -> Nonlinear:
        """``span_rad``: the units' spans as the spec lays them out, where they are groups;
        ``k1``: the spec's lens'."""
        return cls(rotation_rad, (0.0,) * leds, (leak,) * leds, 1.0, (0.0, 0.0), (0.0, 0.0), 2.2, tuple(span_rad),
                   k1)

    def alignment(self, turn: float = 0.0, k2: float = 0.0) -> Alignment:
        """The membrane's alignment against the spec's camera (scenes.profile), turned by
        ``turn`` rad more (an LED's azimuth), its lens' k2 given."""
        return Alignment(self.rotation_rad + turn, self.scale, self.shift_px, distortion=(self.k1, k2))


def _bounds(leds: int, leak: bool, arcs: list | None = None, k1: float | None = None) -> list[tuple[float, float]]:
    """The search's bounds; ``arcs`` (ImageModel.arcs): a span in [0, 2 pi] for each
    unit of more than one LED (a single LED's is fixed); ``k1``: the lens' k1 held
    there, None: searched in K1_BOUNDS."""
    b = AZIMUTH_BOUND_RAD
    spans = [] if arcs is None else [(0.0, 2 * math.pi) if len(a) > 1 else (0.0, 0.0) for a in arcs]
    return ([(-4 * math.pi, 4 * math.pi)] + [(-b, b)] * leds + [(0.0, 1.0 if leak else 0.0)] * leds
            + [tuple(map(math.log, SCALE_BOUNDS))] + [(-SHIFT_BOUND_PX, SHIFT_BOUND_PX)] * 2
            + [(MIN_EDGE_ILLUMINATION, 1.0), (0.0, 1.0)] + [GAMMA_BOUNDS] + spans
            + [K1_BOUNDS if k1 is None else (k1, k1)])


class ImageModel:
    """The image model of the module doc at a film's resolution, for one basis."""

    def __init__(self, basis: np.ndarray, names, camera: Camera, circle: tuple[float, float, float] | None,
                 arcs: list | None = None, spans: tuple = (), rendered: Camera | None = None, lens: bool = False,
                 known_alignment: bool = False, response: np.ndarray | None = None, webcam: bool = False):
        """basis (h, w, S) per unit flux of sources ``names``, taken with the camera
        ``rendered`` (default: ``camera``, the spec's; ``basis_camera`` sees wider, so the
        fitted lens may too); ``arcs`` and ``spans`` (``basis_layout``): each unit's LEDs
        along its arc as shares of its span (Nonlinear.span_rad, which starts at
        ``spans``), its source rendered at the arc's centre; None: each unit is one LED.
        ``lens``: the lens' k1 is fitted (else held at the spec's). ``known_alignment``:
        the real camera is the spec's (module doc): the rotation, scale, shift and k1 are
        held there (``lens`` must be False). ``response``: (S, 3) each source's film
        response (the basis' ``response``): the gains follow each LED's (module doc); None:
        a free gain per LED and channel. ``webcam``: the camera's response held to a
        webcam's (WEBCAM_GAMMA, WEBCAM_BLACK)."""
        if known_alignment and lens:
            raise ValueError("ImageModel: a known alignment holds the lens at the spec's; lens=True fits it")
        self.A = np.asarray(basis, np.float64)
        self.h, self.w, self.S = self.A.shape
        self.led = led_of_source(names)
        self.leds = int(self.led.max()) + 1
        self.has_leak = is_leak(names)
        self.camera = camera
        self.rendered = camera if rendered is None else rendered
        self._lens_rays: tuple = (None, None)  # (the real lens, its rays at the film): ``moved``
        self.lens = lens
        self.known_alignment = bool(known_alignment)
        r = circle_radius(circle, (self.h, self.w), (camera.height, camera.width))
        self.inside = r <= 1.0 if circle is not None else np.ones(r.shape, bool)
        self.r = np.minimum(r, 1.0)
        self.arcs = None if arcs is None else [np.asarray(a, np.float64) for a in arcs]
        self.spans = tuple(float(v) for v in spans)
        self._arcs: dict = {}  # (source, turns) -> the basis' arc image (``_arc``)
        #: the offsets' cap as an image value without light (WEBCAM_BLACK), None: free
        self.black = WEBCAM_BLACK if webcam else None
        #: (L, 3) each LED's film response, its own source's, over its largest; None: free gains
        self.response = None
        if response is not None:
            response = np.asarray(response, np.float64)
            if response.shape != (self.S, 3) or not np.all(np.isfinite(response)) or np.any(response < 0):
                raise ValueError(f"ImageModel: response must be ({self.S}, 3) finite and >= 0, got {response.shape}")
            own = np.stack([response[np.flatnonzero((self.led == m) & ~self.has_leak)[0]] for m in range(self.leds)])
            if np.any(own.max(axis=1) <= 0):
                raise ValueError("ImageModel: an LED's film response is zero in every channel")
            self.response = own / own.max(axis=1, keepdims=True)
        if self.arcs is not None and not len(self.arcs) == len(self.spans) == self.leds:
            raise ValueError(f"arcs: {len(self.arcs)} units and {len(self.spans)} spans for a basis of {self.leds} "
                             "LEDs")

    def nonlinear(self, z: np.ndarray) -> Nonlinear:
        """The Nonlinear of a searched vector for this model's units."""
        return Nonlinear.from_vector(z, self.leds, self.arcs is not None)

    def start(self, rotation_rad: float = 0.0, leak: float = 0.0) -> Nonlinear:
        """A search's start: the LEDs where the spec has them, its lens."""
        return Nonlinear.start(self.leds, rotation_rad, leak, self.spans, self.camera.k1)

    def bounds(self, leak: bool) -> list[tuple[float, float]]:
        """The search's bounds (``_bounds``) for this model's units and lens; with a known
        alignment, the rotation, scale and shift held at the camera's."""
        bounds = _bounds(self.leds, leak, self.arcs, None if self.lens else self.camera.k1)
        if self.black is not None:
            bounds = [WEBCAM_GAMMA if name == "gamma" else b for name, b in zip(self.start().names(), bounds)]
        if self.known_alignment:
            held = ("rotation_rad", "log_scale", "shift_u", "shift_v")
            bounds = [(0.0, 0.0) if name in held else b for name, b in zip(self.start().names(), bounds)]
        return bounds

    def moved(self, image: np.ndarray, nl: Nonlinear, turn: float, variance: bool = False) -> np.ndarray:
        """(h, w) ``image`` turned by ``turn`` rad (an LED's azimuth; 0 for the membrane)
        and moved by the alignment: the point seen at p came from T^-1 p (unshift, rotate
        back, unscale about the principal point). ``variance``: ``image`` is a variance map and
        the result the variance of the moved image (bilinear weights w: sum w^2 sigma^2,
        with sigma^2 taken as locally even), which interpolation lowers up to fourfold."""
        alignment = nl.alignment(turn, self.camera.k2)
        # the real lens' rays are the same for every source of one evaluation: kept
        lens = alignment.lens(self.camera)
        if self._lens_rays[0] != lens:
            self._lens_rays = (lens, lens.scaled(self.w, self.h).slopes())
        coords = alignment.sampling((self.h, self.w), self.camera, rendered=self.rendered, slopes=self._lens_rays[1])
        out = ndimage.map_coordinates(image, coords, order=1, mode="nearest")
        if variance:
            f = coords - np.floor(coords)
            out = out * np.prod(np.square(1.0 - f) + np.square(f), axis=0)
        return out

    def turns(self, nl: Nonlinear, m: int) -> list[float]:
        """Unit m's LEDs' azimuths, rad, from where its source was rendered: its offset,
        plus each LED's place along its arc."""
        if self.arcs is None:
            return [nl.led_azimuth_rad[m]]
        return [nl.led_azimuth_rad[m] + nl.span_rad[m] * float(o) for o in self.arcs[m]]

    def _mixed(self, images: np.ndarray, nl: Nonlinear, power: int, azimuths: bool = True) -> np.ndarray:
        """(h, w, L) each unit's image of per-source ``images`` (h, w, S): its source and
        leak mixed by the leak share (raised to ``power``: 2 for variances) and moved by
        the alignment; with ``azimuths`` turned by each LED's azimuth and, for a group,
        summed along its arc; without, moved with the membrane only (a tap's change,
        rendered with every LED where it sits: ``calibrate_taps.tap_spec``)."""
        out = np.zeros((self.h, self.w, self.leds))
        for m in range(self.leds):
            f = nl.leak[m]
            turns = self.turns(nl, m) if azimuths else [0.0]
            for k in np.nonzero(self.led == m)[0]:
                share = (f if self.has_leak[k] else 1.0 - f) ** power
                if share > 0 and (self.arcs is None or not azimuths):
                    out[..., m] += share * self.moved(images[..., k], nl, turns[0], power == 2)
                elif share > 0:
                    out[..., m] += share * self.moved(self._arc(images, k, tuple(turns)), nl, 0.0, power == 2)
        return out

    def _arc(self, images: np.ndarray, k: int, turns: tuple) -> np.ndarray:
        """(h, w) source k's image summed over its unit's LEDs along the arc: turned by
        each of ``turns`` about the principal point, before the alignment (which turns,
        scales and shifts about the same point, so it commutes with the turns). Cached
        for the basis, as a fit's finite differences move one unit's arc at a time."""
        key = (k, turns)
        if images is self.A and key in self._arcs:
            return self._arcs[key]
        still = Alignment()
        out = sum(ndimage.map_coordinates(images[..., k], still.sampling((self.h, self.w), self.rendered, t), order=1,
                                          mode="nearest") for t in turns)
        if images is self.A:
            if len(self._arcs) >= ARC_CACHE:
                self._arcs.clear()
            self._arcs[key] = out
        return out

    def falloff(self, nl: Nonlinear) -> np.ndarray:
        """(h, w) the lens' relative illumination, 0 outside the image circle."""
        return np.where(self.inside, relative_illumination(nl.vignetting, self.r), 0.0)

    def warped(self, nl: Nonlinear) -> np.ndarray:
        """(h, w, L) each LED's image, (1 - leak) its own source plus leak its core
        leak's, moved by the LED's alignment."""
        return self._mixed(self.A, nl, 1)

    def design(self, nl: Nonlinear) -> np.ndarray:
        """(h, w, L) the warped LED images times the lens' fall-off (0 outside the circle)."""
        return self.warped(nl) * self.falloff(nl)[..., None]

    def design_variance(self, variance: np.ndarray, nl: Nonlinear) -> np.ndarray:
        """(h, w, L) the variance of ``design`` given the basis' (h, w, S) variance
        (independent sources and pixels)."""
        return self._mixed(np.asarray(variance, np.float64), nl, 2) * np.square(self.falloff(nl))[..., None]

    def prediction_variance(self, variance: np.ndarray, nl: Nonlinear, gains: np.ndarray, draws: int = 8
                            ) -> np.ndarray:
        """(h, w, 3) the expected squared error of the modelled image (before clipping at
        saturation) that the basis' variance (h, w, S) causes: the linear image's noise
        (Gaussian, through the gains) drawn ``draws`` times through the response. (The
        response's slope is unbounded at black, so its first-order estimate overstated the
        error of dim images two- to threefold.)"""
        lin = self.design(nl) @ gains
        sd = np.sqrt(self.design_variance(variance, nl) @ np.square(gains))
        rng = np.random.default_rng(0)
        clean = np.power(np.maximum(lin, 0.0), 1.0 / nl.gamma)
        out = np.zeros_like(lin)
        for _ in range(draws):
            out += np.square(np.power(np.maximum(lin + sd * rng.standard_normal(lin.shape), 0.0), 1.0 / nl.gamma) - clean)
        return out / draws

    def tap_design(self, change: np.ndarray, nl: Nonlinear) -> np.ndarray:
        """(h, w, L) ``design`` of a tap whose per-source change from the no-contact basis
        is ``change`` (h, w, S), rendered in the membrane's frame: the change moves with
        the membrane (the rotation without the LEDs' azimuths), the rest as ``design``."""
        return (self.warped(nl) + self._mixed(change, nl, 1, azimuths=False)) * self.falloff(nl)[..., None]

    def render(self, nl: Nonlinear, gains: np.ndarray, offset, saturation, change: np.ndarray | None = None) -> np.ndarray:
        """(h, w, 3) the modelled real image (scenes.profile.camera_response); with a
        tap's ``change`` (see tap_design), that tap's."""
        response = CameraProfile(gamma=nl.gamma, offset=tuple(offset), saturation=tuple(saturation),
                                 vignetting=nl.vignetting)
        linear = self.warped(nl) if change is None else self.warped(nl) + self._mixed(change, nl, 1, azimuths=False)
        return camera_response(linear @ gains, response, self.falloff(nl))


def solve_gains(X: np.ndarray, y: np.ndarray, clipped: np.ndarray, gamma: float, weight: np.ndarray | None = None,
                iterations: int = 4, black: float | None = None) -> tuple[np.ndarray, float]:
    """One channel's non-negative gains (S,) and offset for pixels X (N, S), real values
    y (N,) with ``clipped`` (N,) censored: least squares in linear units (y^gamma), the
    censored pixels entering only where the prediction falls below the clip level.
    ``black``: the offset at most black^gamma (an image value of ``black`` without light)."""
    target = np.power(y, gamma)
    level = CLIP_LEVEL**gamma
    sw = np.ones(len(y)) if weight is None else np.sqrt(weight)
    use = ~clipped
    Xo = np.c_[X, np.ones(len(y))]
    coef = np.zeros(Xo.shape[1])
    for _ in range(iterations):
        if use.sum() < Xo.shape[1]:
            break
        coef = _nonnegative(Xo[use] * sw[use, None], target[use] * sw[use], None if black is None else black**gamma)
        below = clipped & (Xo @ coef < level)
        new = ~clipped | below
        if np.array_equal(new, use):
            break
        use = new
    offset = min(float(coef[-1]), 1.0)
    return coef[:-1], offset


def _nonnegative(A: np.ndarray, b: np.ndarray, cap: float | None = None, capped: int = 1) -> np.ndarray:
    """argmin |A x - b| over x >= 0 (``scipy.optimize.nnls``), the last ``capped``
    coefficients also at most ``cap`` where given (``scipy.optimize.lsq_linear``'s
    bounded-variable least squares)."""
    if cap is None:
        return optimize.nnls(A, b)[0]
    upper = np.full(A.shape[1], np.inf)
    upper[A.shape[1] - capped:] = cap
    # (clipped: the solver may leave a coefficient at its bound a rounding error past it)
    return np.clip(optimize.lsq_linear(A, b, bounds=(0.0, upper), method="bvls").x, 0.0, upper)


def _rank_one_start(X, Y, clipped, gamma, response, weight, black=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(p, w, offsets): the free gains G (``solve_gains``, per channel) and the p and w that
    make R_mc p_m w_c nearest them, by alternating least squares on the (L, 3) gains."""
    L = X.shape[1]
    G, offset = np.zeros((L, 3)), np.zeros(3)
    for c in range(3):
        G[:, c], offset[c] = solve_gains(X, Y[:, c], clipped[:, c], gamma, weight, black=black)
    power, balance = np.ones(L), np.ones(3)
    for _ in range(200):
        balance = np.maximum((G * response * power[:, None]).sum(0), 0.0) / np.maximum(
            (np.square(response) * np.square(power)[:, None]).sum(0), 1e-30)
        power = np.maximum((G * response * balance[None, :]).sum(1), 0.0) / np.maximum(
            (np.square(response) * np.square(balance)[None, :]).sum(1), 1e-30)
        if power.max() > 0:
            balance, power = balance * power.max(), power / power.max()
    return (power if power.max() > 0 else np.ones(L)), balance, offset


def solve_spectral_gains(X: np.ndarray, Y: np.ndarray, clipped: np.ndarray, gamma: float, response: np.ndarray,
                         weight: np.ndarray | None = None, iterations: int = 3, black: float | None = None
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Gains g_mc = p_m R_mc w_c (L, 3) and offsets (3,) for pixels X (N, L), real values
    Y (N, 3) with ``clipped`` (N, 3) censored, each LED's film response R (L, 3): least
    squares in linear units (Y^gamma) over the unclipped pixels by alternating
    non-negative solves, each linear: the white balances w with the offsets for the powers
    p, then the powers with the offsets for the white balances (the powers' scale is the
    white balance's: max p = 1), from the free gains' nearest such product
    (``_rank_one_start``); then each channel's balance and offset once more with the
    censoring (``solve_gains``). ``black``: every offset at most black^gamma."""
    L = X.shape[1]
    target = np.power(Y, gamma)
    sw = np.ones(len(Y)) if weight is None else np.sqrt(weight)
    use = ~clipped
    power, balance, offset = _rank_one_start(X, Y, clipped, gamma, response, weight, black)
    cap = None if black is None else black**gamma
    rhs = np.concatenate([target[use[:, c], c] * sw[use[:, c]] for c in range(3)])
    one = [np.zeros((int(use[:, c].sum()), 3)) for c in range(3)]
    for c in range(3):
        one[c][:, c] = sw[use[:, c]]
    for _ in range(iterations):
        for c in range(3):
            column = X[use[:, c]] @ (power * response[:, c])
            balance[c], offset[c] = _nonnegative(np.c_[column, np.ones(len(column))] * sw[use[:, c], None],
                                                 target[use[:, c], c] * sw[use[:, c]], cap)
        if not np.any(balance > 0) or len(rhs) < L + 3:
            break
        rows = np.concatenate([np.c_[X[use[:, c]] * (response[:, c] * balance[c]) * sw[use[:, c], None], one[c]]
                               for c in range(3)])
        coef = _nonnegative(rows, rhs, cap, capped=3)
        new, offset = coef[:L], coef[L:]
        if not new.max() > 0:
            break
        balance = balance * new.max()
        new = new / new.max()
        done = np.allclose(new, power, rtol=1e-6, atol=1e-9)
        power = new
        if done:
            break
    for c in range(3):  # each channel's balance and offset for the powers found, with the censoring
        scale, offset[c] = solve_gains((X @ (power * response[:, c]))[:, None], Y[:, c], clipped[:, c], gamma, weight,
                                       black=black)
        balance[c] = float(scale[0])
    return power[:, None] * response * balance[None, :], offset
