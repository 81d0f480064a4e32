"""Calibrate the physically based reference to a real sensor unit from its no-contact image.

The image is linear in each emitter's power and the transport is grey, so the reference
renders one grey basis image per source once (``emitter_basis``: each LED, and each LED's
leak into the glass core, per unit flux) and a real image is modelled as

    I_c(p) = clip((V(p) sum_s g_sc A_s(T_m(s)^-1 p) + o_c) ** (1 / gamma), 0, sat_c)

- A_s : source s's basis image, rendered with the physical effects (absorption,
  scattering, coating albedo) of one point of a coarse grid; common random numbers (one
  seed) across the grid, so differences between grid points are not noise;
- T_m : the membrane's alignment for the source's LED m: a rotation about the principal
  point by theta + phi_m (the global rotation and each LED's azimuth offset, which the
  rotationally symmetric membrane turns into an image rotation), a scale and a shift;
  the image circle is the lens' and does not move;
- g_sc >= 0 : each source's gain in each channel, the product of its power, its spectrum
  under the camera's filters and the white balance, which one image cannot separate: they
  are fitted together, by non-negative least squares, for every value of the nonlinear
  parameters (variable projection), and the core leak fraction is read from them;
- V : the lens' relative illumination 1 + a1 r^2 + a2 r^4, non-increasing and positive;
- gamma, o_c, sat_c : the camera's response, black offset and clip level. Clipped real
  pixels are censored: a prediction above the clip level there costs nothing.

The nonlinear parameters (theta, phi_m, scale, shift, a1, a2, gamma) are searched by
Powell's method from several rotations; the physical ones on the grid. The image is cut
into SECTORS angular sectors about the image circle's centre: even ones fit, odd ones
judge (held-out R^2 per unsaturated channel), and the fit is bootstrapped over the
training sectors for intervals.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage, optimize

from scenes.camera import Camera
from scenes.images import block_mean
from scenes.profile import (
    Alignment,
    CameraProfile,
    Profile,
    camera_response,
    circle_radius,
    relative_illumination,
)
from scenes.spec import SensorSpec

from .effects import Effects

#: Angular sectors of the image circle: even ones fit, odd ones judge.
SECTORS = 12
#: A real pixel at or above this (in [0, 1]) in a channel is clipped there.
CLIP_LEVEL = 254.0 / 255.0
#: A channel clipped over more than this share of the image circle is "saturated": it
#: is censored in the fit and not judged.
SATURATED_SHARE = 0.5
#: Pixels above this in any channel are inside the real image circle.
CIRCLE_THRESHOLD = 8.0 / 255.0
#: Bounds of the fit: LED azimuth offsets (rad) from the spec's, scale, shift (px at the
#: camera's resolution), response exponent.
AZIMUTH_BOUND_RAD = math.radians(25.0)
SCALE_BOUNDS = (0.8, 1.25)
SHIFT_BOUND_PX = 40.0
GAMMA_BOUNDS = (0.5, 3.0)
#: The lens' fall-off V = 1 + a1 r^2 + a2 r^4 is searched as V(1) = 1 + a1 + a2 in
#: [MIN_EDGE_ILLUMINATION, 1] and the r^4 share a2 / (a1 + a2) in [0, 1]: every value
#: searched is a lens a profile accepts (non-increasing, positive).
MIN_EDGE_ILLUMINATION = 0.02
#: Starting rotations of the search (the LEDs repeat every 120 deg but their colours do not).
ROTATION_STARTS = 12
#: The default grid of physical effects searched (common random numbers across it).
GRID = {"absorption_per_m": (5.0, 20.0, 80.0), "scattering_per_m": (10.0, 50.0, 250.0)}
#: Effects the basis is rendered with besides the grid's: the leak sources exist (their
#: power is fitted) and the coating albedo is tied (it scales every source like a power).
BASIS_EFFECTS = {"core_light_leak": 0.5}
#: With taps, the taps are rendered and fitted at this many of the grid's best points by
#: the no-contact fit, and the best joint fit is kept: one no-contact image ranks the
#: grid's absorption and scattering poorly (a blind benchmark's sensor at 80 and 250 per
#: m was fitted at 5 and 10), while a contact's shading depends on them.
TAP_GRID_POINTS = 3
#: Bootstrap resamples of the training sectors.
BOOTSTRAP = 16
#: A fit has converged when Powell's method says so and it either moved off its start
#: (the loss fell by this share) or already leaves less than STUCK_SHARE of the real
#: image's variance: a fit that leaves a large gap without moving stopped at its start.
MIN_IMPROVEMENT = 1e-3
STUCK_SHARE = 0.05


# -- the real image -----------------------------------------------------------------------

def check_real(image: np.ndarray, camera: Camera, name: str = "image") -> np.ndarray:
    """A real (H, W, 3) image in [0, 1] at the camera's size, checked: not blank, not
    saturated almost everywhere."""
    image = np.asarray(image)
    if image.shape != (camera.height, camera.width, 3):
        raise ValueError(f"{name} must be {camera.width}x{camera.height} RGB (the spec's camera), got shape "
                         f"{image.shape}")
    image = image.astype(np.float64)
    if not np.all(np.isfinite(image)) or image.min() < 0 or image.max() > 1:
        raise ValueError(f"{name} must hold finite values in [0, 1]")
    lit = image.max(axis=2) > CIRCLE_THRESHOLD
    if lit.mean() < 0.05:
        raise ValueError(f"{name} is blank: {lit.mean():.1%} of its pixels are above {CIRCLE_THRESHOLD:.3f}")
    clipped = (image >= CLIP_LEVEL).all(axis=2)[lit].mean()
    if clipped > 0.9:
        raise ValueError(f"{name} is saturated almost everywhere: {clipped:.0%} of its lit pixels are clipped in "
                         "every channel; lower the exposure")
    return image


def image_circle(image: np.ndarray) -> tuple[float, float, float] | None:
    """(cx, cy, radius) px of the lit disc of a real image, or None where the optics
    fill the frame (the lit area is more than 98 % of it)."""
    lit = np.asarray(image).max(axis=2) > CIRCLE_THRESHOLD
    lit = ndimage.binary_opening(lit, iterations=2)
    if lit.mean() > 0.98:
        return None
    v, u = np.nonzero(lit)
    return float(u.mean()), float(v.mean()), float(math.sqrt(lit.sum() / math.pi))


def sector_index(shape: tuple[int, int], centre: tuple[float, float], sectors: int = SECTORS) -> np.ndarray:
    """(H, W) int: the angular sector of each pixel about ``centre`` (u, v)."""
    v, u = np.mgrid[0:shape[0], 0:shape[1]]
    angle = np.mod(np.arctan2(v - centre[1], u - centre[0]), 2 * math.pi)
    return np.minimum((angle / (2 * math.pi) * sectors).astype(int), sectors - 1)


def film_factor(shape: tuple[int, ...], film: tuple[int, int]) -> int:
    """The whole factor k between an (H, W, ...) camera image and the film (w, h)."""
    H, W = shape[:2]
    k = H // film[1]
    if k < 1 or k * film[1] != H or k * film[0] != W:
        raise ValueError(f"the film {film[0]}x{film[1]} must divide the camera's {W}x{H} evenly")
    return k


# -- the basis ----------------------------------------------------------------------------

def emitter_basis(spec: SensorSpec, mesh, camera: Camera, effects: Effects, film: tuple[int, int],
                  photons: int = 1 << 18, spp: int = 32, passes: int = 2, seed: int = 0,
                  use_cache: bool = True, depth: np.ndarray | None = None,
                  ref_depth: np.ndarray | None = None, solids=None, no_contact_runs: int = 0) -> dict:
    """One grey image per source (``pbr_tactile.scene.led_sources``, with leaks) of the
    sensor: ``mean`` (h, w, S) per unit flux, ``variance``, ``names`` (S,), ``response``
    (S, 3) the film's response to each source at the effects' powers. Without ``depth``
    the no-contact sensor; with a contact depth map (H, W) m and the no-contact
    ``ref_depth``, that contact (the same seed as the no-contact basis: common random
    numbers, so their difference is the contact's change with little noise). Cached on
    disk (scenes.cache) by everything it depends on. ``solids``: the membrane's
    ``ElastomerBuilder`` for this spec and camera, kept across renders (it refines and
    checks the membrane once; None builds one). ``no_contact_runs``: the photon map as the
    sensor's cached no-contact map (this many runs per pass) plus the contact's change, as
    a dataset renders it (``pbr_tactile.render.reference``); 0 traces every photon each time."""
    from scenes.cache import cached, make_key

    from .nocontact import CACHE_VERSION
    from .render import reference, source_response
    from .scene import led_sources
    from .variant import choose_variant

    variant = choose_variant().variant()
    width, height = film
    if (depth is None) != (ref_depth is None):
        raise ValueError("emitter_basis: a contact needs both depth and ref_depth")
    contact = [] if depth is None else [np.asarray(depth, np.float32), np.asarray(ref_depth, np.float32)]
    key = make_key("basis", 1, CACHE_VERSION, variant, dataclasses.asdict(spec), np.asarray(mesh.vertices),
                   effects.to_dict(), [width, height], photons, spp, passes, seed, *contact,
                   *([no_contact_runs] if no_contact_runs else []))

    def build():
        est = reference(depth, ref_depth, mesh, spec, camera, effects, spp=spp * passes, width=width, height=height,
                        seed=seed, variant=variant, passes=passes, photons=photons, per_source=True, solids=solids,
                        no_contact_runs=no_contact_runs)
        sources = led_sources(spec, effects)
        return {"mean": est.mean, "variance": est.variance, "names": np.array([s["name"] for s in sources]),
                "response": source_response(sources, effects)}

    return cached("pbr-calibration-basis", key, build, use_cache=use_cache)


def led_of_source(names) -> np.ndarray:
    """(S,) the LED index of each source name (``led<m>`` or ``led<m>_leak``)."""
    return np.array([int(str(n)[3:].split("_")[0]) for n in names])


# -- the model ----------------------------------------------------------------------------

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

    def vector(self) -> np.ndarray:
        """The searched coordinates: the scale as its log, the fall-off as V(1) and its
        r^4 share (see MIN_EDGE_ILLUMINATION), then the spans."""
        total = -sum(self.vignetting)
        quartic = -self.vignetting[1] / total if total > 0 else 0.0
        return np.r_[self.rotation_rad, self.led_azimuth_rad, self.leak, math.log(self.scale), self.shift_px,
                     1.0 - total, quartic, self.gamma, self.span_rad]

    @classmethod
    def from_vector(cls, z: np.ndarray, leds: int, arcs: bool = False) -> Nonlinear:
        """``leds`` units; ``arcs``: the vector ends with their spans."""
        z = np.asarray(z, np.float64)
        n = leds
        total, quartic = 1.0 - float(z[4 + 2 * n]), float(z[5 + 2 * n])
        return cls(float(z[0]), tuple(map(float, z[1:1 + n])), tuple(map(float, z[1 + n:1 + 2 * n])),
                   float(math.exp(z[1 + 2 * n])), (float(z[2 + 2 * n]), float(z[3 + 2 * n])),
                   (-total * (1.0 - quartic), -total * quartic), float(z[6 + 2 * n]),
                   tuple(map(float, z[7 + 2 * n:7 + 3 * n])) if arcs else ())

    def tied(self) -> Nonlinear:
        """The same image with the LED azimuth offsets' mean moved into the rotation,
        which is then wrapped to (-pi, pi]: one no-contact image sees only their sums,
        and this is the tie the profile reports (see NOT_IDENTIFIABLE)."""
        mean = float(np.mean(self.led_azimuth_rad)) if self.led_azimuth_rad else 0.0
        rotation = math.remainder(self.rotation_rad + mean, 2 * math.pi)
        return dataclasses.replace(self, rotation_rad=rotation,
                                   led_azimuth_rad=tuple(a - mean for a in self.led_azimuth_rad))

    @classmethod
    def start(cls, leds: int, rotation_rad: float = 0.0, leak: float = 0.0, span_rad: tuple = ()) -> Nonlinear:
        """``span_rad``: the units' spans as the spec lays them out, where they are groups."""
        return cls(rotation_rad, (0.0,) * leds, (leak,) * leds, 1.0, (0.0, 0.0), (0.0, 0.0), 2.2, tuple(span_rad))


def _bounds(leds: int, leak: bool, arcs: list | None = None) -> list[tuple[float, float]]:
    """The search's bounds; ``arcs`` (ImageModel.arcs): a span in [0, 2 pi] for each
    unit of more than one LED (a single LED's is fixed)."""
    b = AZIMUTH_BOUND_RAD
    spans = [] if arcs is None else [(0.0, 2 * math.pi) if len(a) > 1 else (0.0, 0.0) for a in arcs]
    return ([(-4 * math.pi, 4 * math.pi)] + [(-b, b)] * leds + [(0.0, 1.0 if leak else 0.0)] * leds
            + [tuple(map(math.log, SCALE_BOUNDS))] + [(-SHIFT_BOUND_PX, SHIFT_BOUND_PX)] * 2
            + [(MIN_EDGE_ILLUMINATION, 1.0), (0.0, 1.0)] + [GAMMA_BOUNDS] + spans)


def basis_layout(spec: SensorSpec) -> tuple[SensorSpec, list | None, tuple, np.ndarray, np.ndarray]:
    """How the basis renders a spec's LEDs: the spec it renders (its single LEDs, then
    one LED of each group's build at the arc's centre: a group's LEDs differ only by a
    turn about the axis, which the rotationally symmetric membrane turns into an image
    rotation, so one render per group stands for all of them), each unit's arc offsets
    (``LEDGroup.offsets``; None without groups) and span (rad; () without groups), and
    for each of ``spec.leds`` its unit (L,) and its offset along the arc (L,) as a share
    of the span."""
    if not spec.led_groups:
        return spec, None, (), np.arange(len(spec.leds)), np.zeros(len(spec.leds))
    singles = [led for led in spec.leds if led.group is None]
    groups = list(spec.led_groups)
    rendered = singles + [g.led_at(g.arc_centre_rad, g.name) for g in groups]
    arcs = [np.zeros(1)] * len(singles) + [g.offsets() for g in groups]
    spans = (0.0,) * len(singles) + tuple(g.arc_span_rad for g in groups)
    unit, share = [], []
    for led in spec.leds:
        if led.group is None:
            unit.append(singles.index(led))
            share.append(0.0)
        else:
            g = [x.name for x in groups].index(led.group)
            unit.append(len(singles) + g)
            share.append(float(groups[g].offsets()[[x.name for x in groups[g].leds()].index(led.name)]))
    return spec.replace(leds=tuple(rendered), led_groups=()), arcs, spans, np.array(unit), np.array(share)


class ImageModel:
    """The image model of the module doc at a film's resolution, for one basis."""

    def __init__(self, basis: np.ndarray, names, camera: Camera, circle: tuple[float, float, float] | None,
                 arcs: list | None = None, spans: tuple = ()):
        """basis (h, w, S) per unit flux of sources ``names``; ``arcs`` and ``spans``
        (``basis_layout``): each unit's LEDs along its arc as shares of its span
        (Nonlinear.span_rad, which starts at ``spans``), its source rendered at the arc's
        centre; None: each unit is one LED."""
        self.A = np.asarray(basis, np.float64)
        self.h, self.w, self.S = self.A.shape
        self.led = led_of_source(names)
        self.leds = int(self.led.max()) + 1
        self.has_leak = np.array([str(n).endswith("_leak") for n in names])
        self.camera = camera
        r = circle_radius(circle, (self.h, self.w), (camera.height, camera.width))
        self.inside = r <= 1.0 if circle is not None else np.ones(r.shape, bool)
        self.r = np.minimum(r, 1.0)
        self.arcs = None if arcs is None else [np.asarray(a, np.float64) for a in arcs]
        self.spans = tuple(float(v) for v in spans)
        if self.arcs is not None and not len(self.arcs) == len(self.spans) == self.leds:
            raise ValueError(f"arcs: {len(self.arcs)} units and {len(self.spans)} spans for a basis of {self.leds} "
                             "LEDs")

    def nonlinear(self, z: np.ndarray) -> Nonlinear:
        """The Nonlinear of a searched vector for this model's units."""
        return Nonlinear.from_vector(z, self.leds, self.arcs is not None)

    def start(self, rotation_rad: float = 0.0, leak: float = 0.0) -> Nonlinear:
        """A search's start: the LEDs where the spec has them."""
        return Nonlinear.start(self.leds, rotation_rad, leak, self.spans)

    def moved(self, image: np.ndarray, nl: Nonlinear, turn: float, variance: bool = False) -> np.ndarray:
        """(h, w) ``image`` turned by ``turn`` rad (an LED's azimuth; 0 for the membrane)
        and moved by the alignment: the point seen at p came from T^-1 p (unshift, rotate
        back, unscale about the principal point). ``variance``: ``image`` is a variance map and
        the result the variance of the moved image (bilinear weights w: sum w^2 sigma^2,
        with sigma^2 taken as locally even), which interpolation lowers up to fourfold."""
        turn = nl.rotation_rad + turn
        coords = Alignment(0.0, nl.scale, nl.shift_px).sampling((self.h, self.w), self.camera, turn)
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
        if not azimuths and self.arcs is not None:
            raise ValueError("a contact's change with LED groups is not modelled: render it per LED")
        out = np.zeros((self.h, self.w, self.leds))
        for m in range(self.leds):
            f = nl.leak[m]
            turns = self.turns(nl, m) if azimuths else [0.0]
            for k in np.nonzero(self.led == m)[0]:
                share = (f if self.has_leak[k] else 1.0 - f) ** power
                if share > 0:
                    for turn in turns:
                        out[..., m] += share * self.moved(images[..., k], nl, turn, power == 2)
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
                iterations: int = 4) -> tuple[np.ndarray, float]:
    """One channel's non-negative gains (S,) and offset for pixels X (N, S), real values
    y (N,) with ``clipped`` (N,) censored: least squares in linear units (y^gamma), the
    censored pixels entering only where the prediction falls below the clip level."""
    target = np.power(y, gamma)
    level = CLIP_LEVEL**gamma
    sw = np.ones(len(y)) if weight is None else np.sqrt(weight)
    use = ~clipped
    Xo = np.c_[X, np.ones(len(y))]
    coef = np.zeros(Xo.shape[1])
    for _ in range(iterations):
        if use.sum() < Xo.shape[1]:
            break
        coef, _ = optimize.nnls(Xo[use] * sw[use, None], target[use] * sw[use])
        below = clipped & (Xo @ coef < level)
        new = ~clipped | below
        if np.array_equal(new, use):
            break
        use = new
    offset = min(float(coef[-1]), 1.0)
    return coef[:-1], offset


# -- the fit ------------------------------------------------------------------------------

@dataclass
class ImageFit:
    """A fitted image model: nonlinear parameters, gains (L, 3), offset (3,), loss."""

    nl: Nonlinear
    gains: np.ndarray
    offset: np.ndarray
    loss: float
    start_loss: float
    converged: bool
    evaluations: int
    #: the part of ``loss`` the basis' Monte Carlo noise is expected to add (``_debiased``)
    noise: float = 0.0


@dataclass
class TapView:
    """One tap in a fit: its per-source change from the no-contact basis (h, w, S; see
    ImageModel.tap_design) with the LEDs where the spec has them, the real tap image (h,
    w, 3), the pixels it is fitted on (h, w) and its weight (a bootstrap's multiplicity).
    ``slope`` and ``curve`` (h, w, S), where given, make the change depend on each LED's
    azimuth a: change + a slope + a^2 curve (``pbr_tactile.calibrate_taps``)."""

    change: np.ndarray
    real: np.ndarray
    pixels: np.ndarray
    weight: float = 1.0
    slope: np.ndarray | None = None
    curve: np.ndarray | None = None

    def at(self, nl: Nonlinear, led: np.ndarray) -> np.ndarray:
        """(h, w, S) the change with the LEDs at ``nl``'s azimuths; ``led`` (S,) each
        source's LED."""
        if self.slope is None:
            return self.change
        a = np.asarray(nl.led_azimuth_rad, np.float64)[led]
        return self.change + a * self.slope + a * a * self.curve


class ImageFitter:
    """Fits an ImageModel to a real image on a set of pixels, and to taps if given (see
    the module doc and ``pbr_tactile.calibrate_taps``)."""

    def __init__(self, model: ImageModel, real: np.ndarray, fit_pixels: np.ndarray, weight: np.ndarray | None = None,
                 leak: bool = True, taps: list[TapView] = (), common_turn: bool = False):
        """fit_pixels (h, w) bool; weight (h, w) per-pixel weights (a bootstrap's
        multiplicities) or None; leak False: no light into the core (the leak fixed at 0);
        taps: fitted together with the image, their pixels stacked with its;
        common_turn: the LEDs' azimuths tied to one value, the ring's turn against the
        membrane (see NOT_IDENTIFIABLE_WITH_TAPS)."""
        self.model, self.real = model, np.asarray(real, np.float64)
        self.leak = leak
        self.common_turn = common_turn
        self.pixels = fit_pixels & model.inside
        self.clipped = self.real >= CLIP_LEVEL
        self.weight = None if weight is None else np.asarray(weight, np.float64)[self.pixels]
        self.taps = [t for t in taps if t.weight > 0]
        # the stacked real pixels, censoring and weights of the image and the taps
        views = [(self.real, self.pixels, np.ones(int(self.pixels.sum())) if weight is None else self.weight)]
        views += [(np.asarray(t.real, np.float64), t.pixels & model.inside,
                   np.full(int((t.pixels & model.inside).sum()), float(t.weight))) for t in self.taps]
        self.y = np.concatenate([real_[pixels] for real_, pixels, _ in views])
        self.y_clipped = self.y >= CLIP_LEVEL
        self.w = np.concatenate([w for _, _, w in views])
        # the loss of predicting each channel's mean: the real image's variance
        self.variance = float(np.mean([np.var(self.real[..., c][self.pixels]) for c in range(3)]))

    def design(self, nl: Nonlinear) -> np.ndarray:
        """(N, L) the stacked design rows of the image's and the taps' fitted pixels."""
        falloff = self.model.falloff(nl)[..., None]
        warped = self.model.warped(nl)
        rows = [(warped * falloff)[self.pixels]]
        for t in self.taps:
            change = self.model._mixed(t.at(nl, self.model.led), nl, 1, azimuths=False)
            rows.append(((warped + change) * falloff)[t.pixels & self.model.inside])
        return np.concatenate(rows)

    def solve(self, nl: Nonlinear) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The best gains and offsets for ``nl`` and the weighted, censored residuals,
        whose sum of squares is the mean squared error over pixels and channels."""
        X = self.design(nl)
        w = self.w
        sw = np.sqrt(w / (3 * np.sum(w)))
        weight = None if self.weight is None and not self.taps else w
        gains, offset, residuals = np.zeros((self.model.leds, 3)), np.zeros(3), []
        for c in range(3):
            y, clipped = self.y[:, c], self.y_clipped[:, c]
            gains[:, c], offset[c] = solve_gains(X, y, clipped, nl.gamma, weight)
            pred = np.clip(X @ gains[:, c] + offset[c], 0.0, None) ** (1.0 / nl.gamma)
            residuals.append(sw * np.where(clipped, np.minimum(pred - y, 0.0), pred - y))
        return gains, offset, np.concatenate(residuals)

    def loss(self, z: np.ndarray) -> float:
        """The censored mean squared error at nonlinear parameters ``z``."""
        return float(np.sum(self.solve(self.model.nonlinear(z))[2] ** 2))

    def fit(self, start: Nonlinear, max_evaluations: int = 1500) -> ImageFit:
        """Bounded least squares over the nonlinear parameters from ``start`` (the gains
        solved inside every evaluation: variable projection)."""
        leds = self.model.leds
        bounds = np.array(_bounds(leds, self.leak and self.model.has_leak.any(), self.model.arcs))
        free = bounds[:, 1] > bounds[:, 0]
        z0 = np.clip(start.vector(), bounds[:, 0], bounds[:, 1])
        if self.common_turn:
            # the first LED's azimuth is searched, the others follow it
            z0[1:1 + leds] = np.mean(z0[1:1 + leds])
            free[2:1 + leds] = False
        start_loss = self.loss(z0)

        def full(zf):
            z = z0.copy()
            z[free] = zf
            if self.common_turn:
                z[2:1 + leds] = z[1]
            return z

        def residuals(zf):
            return self.solve(self.model.nonlinear(full(zf)))[2]

        result = optimize.least_squares(residuals, z0[free], bounds=(bounds[free, 0], bounds[free, 1]),
                                        diff_step=1e-3, max_nfev=max_evaluations, x_scale="jac")
        z = full(result.x)
        nl = self.model.nonlinear(z)
        gains, offset, res = self.solve(nl)
        loss = float(np.sum(res**2))
        moved = loss < start_loss * (1 - MIN_IMPROVEMENT)
        small = loss <= STUCK_SHARE * self.variance
        return ImageFit(nl, gains, offset, loss, start_loss, result.status > 0 and (moved or small), int(result.nfev))

    def search(self, rotations: int = ROTATION_STARTS, max_evaluations: int = 2000, keep: int = 2) -> ImageFit:
        """Fit from ``rotations`` evenly spaced starting rotations: each start's gains
        first (a cheap screen), then the ``keep`` best refined in full."""
        leak = 0.3 if self.leak and self.model.has_leak.any() else 0.0
        starts = [self.model.start(2 * math.pi * k / rotations, leak) for k in range(rotations)]
        screened = sorted(starts, key=lambda nl: self.loss(nl.vector()))[:keep]
        fits = [self.fit(nl, max_evaluations) for nl in screened]
        return min(fits, key=lambda f: f.loss)


def r2(pred: np.ndarray, real: np.ndarray, pixels: np.ndarray) -> float:
    """Share of the real pixels' variance the prediction explains."""
    y, p = real[pixels], pred[pixels]
    total = float(np.sum((y - y.mean()) ** 2))
    return float(1 - np.sum((y - p) ** 2) / total) if total > 0 else float("nan")


# -- rendering with a profile ------------------------------------------------------------

def profile_effects(profile: Profile, settings: list[str] | None = None) -> Effects:
    """The reference's effects of a profile (with the leak sources the basis needs),
    then ``settings`` (NAME=VALUE) on top."""
    fitted = {k: v for k, v in profile.reference.get("effects", {}).items()}
    try:
        effects = dataclasses.replace(Effects(), **fitted)
    except TypeError as exc:
        raise ValueError(f"profile reference.effects: {exc}") from None
    effects = effects.with_settings([f"{k}={v}" for k, v in BASIS_EFFECTS.items()])
    return effects.with_settings(settings or [])


def profiled_image(per_source: np.ndarray, names, profile: Profile, camera: Camera) -> np.ndarray:
    """(h, w, S) per-source linear images (``reference(..., per_source=True)`` of
    ``profile.sensor_spec``, whose LEDs are already turned, with ``profile_effects``) ->
    (h, w, 3) the calibrated sensor's image in [0, 1]."""
    ref = profile.reference
    try:
        gains = np.asarray(ref["led_gains"], np.float64)
        leds = len(ref["led_leak"])
        nl = Nonlinear(profile.alignment.rotation_rad, (0.0,) * leds, tuple(ref["led_leak"]),
                       profile.alignment.scale, profile.alignment.shift_px, profile.camera.vignetting,
                       profile.camera.gamma)
    except KeyError as exc:
        raise ValueError(f"the profile has no reference.{exc.args[0]}: it was not calibrated for the reference") from None
    model = ImageModel(per_source, names, camera, profile.camera.image_circle)
    if gains.shape != (model.leds, 3) or len(nl.led_azimuth_rad) != model.leds or len(nl.leak) != model.leds:
        raise ValueError(f"the profile's reference tables are for {gains.shape[0]} LEDs, the render has {model.leds}")
    return model.render(nl, gains, profile.camera.offset, profile.camera.saturation)


# -- calibration from a no-contact image --------------------------------------------------

@dataclass
class Calibration:
    """What ``calibrate_background`` found: the profile, the report (JSON-able) and the
    film-sized images behind it (real, before, after)."""

    profile: Profile
    report: dict
    images: dict


def _grid_points(grid: dict) -> list[dict]:
    names = list(grid)
    points = [{}]
    for name in names:
        points = [{**p, name: float(v)} for p in points for v in grid[name]]
    return points


def _interval(values: np.ndarray) -> list[float]:
    return [float(np.percentile(values, 5)), float(np.percentile(values, 95))]


def calibrate_background(real: np.ndarray, spec: SensorSpec, mesh, camera: Camera, film: tuple[int, int] = (160, 120),
                         grid: dict | None = None, photons: int = 1 << 18, spp: int = 32, passes: int = 2,
                         seed: int = 0, bootstrap: int = BOOTSTRAP, leak: bool = True, use_cache: bool = True,
                         progress=None, taps=None) -> Calibration:
    """Calibrate the reference to one real no-contact image (H, W, 3) in [0, 1], and to
    its sensor's taps if given.

    Fits on the even angular sectors of the image circle and judges on the odd ones (see
    the module doc); ``grid`` maps Effects names to the values searched (default GRID);
    ``leak`` False fits with no light into the glass core. ``taps``
    (``pbr_tactile.calibrate_taps.RealTaps``): rendered at the TAP_GRID_POINTS best grid
    points of the no-contact fit and fitted together with the image there, the best joint
    fit kept, alternate taps held out (see that module). Raises ValueError
    for a bad image; a fit that did not converge is reported (``report["converged"]`` False).
    """
    grid = GRID if grid is None else grid
    for name in grid:
        if name not in Effects.__dataclass_fields__:
            raise ValueError(f"grid: {name!r} is not an effect of the reference ({', '.join(Effects.__dataclass_fields__)})")
    real = check_real(real, camera, "the real no-contact image")
    circle = image_circle(real)
    width, height = film
    factor = film_factor(real.shape, film)
    r = block_mean(real, factor)
    clipped_full = real >= CLIP_LEVEL
    inside_full = real.max(axis=2) > CIRCLE_THRESHOLD
    share = [float(clipped_full[..., c][inside_full].mean()) for c in range(3)]
    saturated = {ch: share[c] > SATURATED_SHARE for c, ch in enumerate("rgb")}
    clipped = block_mean(clipped_full.astype(np.float64), factor) > 0.5
    s = height / camera.height
    centre = (camera.cx, camera.cy) if circle is None else circle[:2]
    sector = sector_index((height, width), ((centre[0] + 0.5) * s - 0.5, (centre[1] + 0.5) * s - 0.5))
    if taps is not None and spec.led_groups:
        raise ValueError(f"sensor {spec.name!r} lays its LEDs out in groups, and a fit with taps needs each tap "
                         "rendered per LED, which is not built yet: calibrate from the no-contact image alone "
                         "(--taps 0)")
    rendered, arcs, spans, unit, share_of_span = basis_layout(spec)
    points = _grid_points(grid)
    base = Effects().with_settings([f"{k}={v}" for k, v in BASIS_EFFECTS.items()])
    fits = []
    for i, point in enumerate(points):
        effects = dataclasses.replace(base, **point)
        basis = emitter_basis(rendered, mesh, camera, effects, film, photons, spp, passes, seed, use_cache)
        model = ImageModel(basis["mean"], basis["names"], camera, circle, arcs, spans)
        train, test = (sector % 2 == 0) & model.inside, (sector % 2 == 1) & model.inside
        fit = ImageFitter(model, r, train, leak=leak).search()
        fits.append((_debiased(fit, model, basis, [train]), point, basis, model))
        if progress is not None:
            progress(i + 1, len(points) + 1)
    fit, point, basis, model = min(fits, key=lambda f: f[0].loss - f[0].noise)
    train, test = (sector % 2 == 0) & model.inside, (sector % 2 == 1) & model.inside
    tap_report, fitted_views = None, []
    if taps is not None:
        candidates, ranking, known = sorted(fits, key=lambda f: f[0].loss - f[0].noise)[:TAP_GRID_POINTS], [], None
        if len(candidates) > 1:
            ranking = [{"effects": p, **_rank_with_taps(taps, f, m, b, r, train, dataclasses.replace(base, **p), spec,
                                                        mesh, camera, film, photons, spp, passes, seed, leak,
                                                        use_cache)} for f, p, b, m in candidates]
            best = int(np.argmin([rank["loss"] - rank["noise"] for rank in ranking]))
            fit, point, basis, model = candidates[best]
            known = ranking[best].pop("known")
        fit, fitted_views, tap_report = _fit_taps(taps, fit, model, basis, r, train, dataclasses.replace(base, **point),
                                                  spec, mesh, camera, film, photons, spp, passes, seed, leak, use_cache,
                                                  known)
        tap_report["grid"] = [{k: v for k, v in rank.items() if k != "known"} for rank in ranking]
    after = model.render(fit.nl, fit.gains, fit.offset, (1.0, 1.0, 1.0))
    default = {name: getattr(Effects(), name) for name in grid}
    same = [b for _, p, b, _ in fits if p == default]
    default_basis = same[0] if same else emitter_basis(
        rendered, mesh, camera, dataclasses.replace(base, **default), film, photons, spp, passes, seed, use_cache)
    before = _uncalibrated(rendered, ImageModel(default_basis["mean"], default_basis["names"], camera, circle, arcs,
                                                spans), r, train)
    judged = {ch: test & ~clipped[..., c] for c, ch in enumerate("rgb")}
    heldout = {ch: r2(after[..., c], r[..., c], judged[ch]) for c, ch in enumerate("rgb")}
    heldout_before = {ch: r2(before[..., c], r[..., c], judged[ch]) for c, ch in enumerate("rgb")}
    mae = {ch: float(np.abs(after[..., c] - r[..., c])[judged[ch]].mean()) for c, ch in enumerate("rgb")}
    mae_before = {ch: float(np.abs(before[..., c] - r[..., c])[judged[ch]].mean()) for c, ch in enumerate("rgb")}
    intervals = _bootstrap(fit, model, r, sector, bootstrap, seed, leak, fitted_views) if bootstrap else {}
    r2_interval = {ch: heldout_interval(after[..., c], r[..., c], judged[ch], sector, seed) for c, ch in enumerate("rgb")}
    fast_table, fast_path = _fast_path_background(r, circle, camera, train, test, clipped, judged, sector, seed)
    nl = fit.nl.tied() if taps is None else dataclasses.replace(
        fit.nl, rotation_rad=math.remainder(fit.nl.rotation_rad, 2 * math.pi))
    data = "one no-contact image" if taps is None else f"one no-contact image and {len(taps.ids)} taps"
    # each LED's own values: its unit's, and its turn from where the spec has it
    led_azimuth = tuple(float(nl.led_azimuth_rad[u] + ((nl.span_rad[u] - spans[u]) * o if spans else 0.0))
                        for u, o in zip(unit, share_of_span))
    profile = Profile(
        sensor=spec.name, leds=tuple(led.name for led in spec.leds),
        alignment=Alignment(nl.rotation_rad, nl.scale, nl.shift_px, led_azimuth),
        camera=CameraProfile(gamma=nl.gamma, offset=tuple(np.clip(fit.offset, 0.0, 1.0)),
                             saturation=tuple(CLIP_LEVEL if saturated[ch] else 1.0 for ch in "rgb"),
                             vignetting=nl.vignetting, image_circle=circle),
        reference={"effects": {**point, "coating_albedo": Effects().coating_albedo},
                   "led_leak": [nl.leak[u] for u in unit], "led_gains": fit.gains[unit].tolist(), "film": [width, height],
                   "photons": photons,
                   "spp": spp, "passes": passes, "seed": seed},
        phong={"ambient": 1.0, "background": fast_table},
        fit={"data": data, "converged": fit.converged, "heldout_r2": heldout,
             "phong_heldout_r2": fast_path["heldout_r2"]})
    report = {
        "converged": fit.converged, "loss": fit.loss, "start_loss": fit.start_loss, "evaluations": fit.evaluations,
        "heldout_r2": heldout, "heldout_r2_interval": r2_interval, "heldout_r2_before": heldout_before, "heldout_mae": mae,
        "heldout_mae_before": mae_before, "saturated": saturated, "clipped_share": dict(zip("rgb", share)),
        "image_circle": circle, "film": [width, height], "sectors": SECTORS,
        "split": "even angular sectors of the image circle fit, odd ones judge",
        "grid": [{"effects": p, "loss": f.loss, "noise": f.noise, "converged": f.converged} for f, p, _, _ in fits],
        "best_effects": point, "parameters": _parameters(fit, tie=taps is None, spec=spec), "intervals": intervals,
        "not_identifiable": NOT_IDENTIFIABLE if taps is None else NOT_IDENTIFIABLE_WITH_TAPS, "fast_path": fast_path,
        "taps": tap_report,
    }
    if taps is not None and fit.converged:
        profile = _fast_path_from_taps(profile, report, spec, mesh, camera, taps, real)
    return Calibration(profile, report, {"real": r, "before": before, "after": after, "fast_path": fast_path.pop("image"),
                                         "judged": np.stack([judged[ch] for ch in "rgb"], -1)})


#: What one no-contact image cannot separate, and how the fit ties it.
NOT_IDENTIFIABLE = [
    "LED power, LED spectrum under the camera's filters, white balance and coating albedo all scale a source's "
    "image per channel: fitted together as each LED's RGB gain (led_gains); the coating albedo is tied at its "
    "default",
    "the global rotation and the LED azimuths: only their sums are seen (alignment.rotation_rad + led_azimuth_rad); "
    "tied by giving the azimuth offsets zero mean, so where contacts appear (the membrane's turn) needs taps",
    "the lens' fall-off (vignetting) and the medium's radial transport (absorption, scattering) both shape the "
    "radial profile; the grid's effects are judged with the fall-off fitted for each",
]


#: What one no-contact image and taps cannot separate.
NOT_IDENTIFIABLE_WITH_TAPS = [
    NOT_IDENTIFIABLE[0], NOT_IDENTIFIABLE[2],
    "each LED's own azimuth about the ring: each LED lights the membrane nearly all round, so on the reference's "
    "images (scattering 50 per m) turning one LED by 0.15 rad changed the no-contact fit's loss by at most 6 %, "
    "with its minimum away from the truth, and fitted one by one with 10 taps they were no closer than zero "
    "(median error 0.57-0.70 of their range's half-width, where 0 scores 0.5); tied to one turn of the ring "
    "against the membrane (every azimuth equal), which the contacts' shading sees",
]


def _parameters(fit: ImageFit, tie: bool = True, spec: SensorSpec | None = None) -> dict:
    """The fitted values as plain data, per unit (an LED, or an LED group); ``tie``: the
    rotation and azimuths tied (only one image: see NOT_IDENTIFIABLE), else the rotation
    only wrapped. With the ``spec`` of LED groups, each group's fitted arc too (its
    centre's turn against the membrane is the rotation plus its azimuth offset)."""
    nl = fit.nl.tied() if tie else dataclasses.replace(fit.nl, rotation_rad=math.remainder(fit.nl.rotation_rad,
                                                                                            2 * math.pi))
    out = {"rotation_rad": nl.rotation_rad, "led_azimuth_rad": list(nl.led_azimuth_rad), "led_leak": list(nl.leak),
           "scale": nl.scale, "shift_px": list(nl.shift_px), "vignetting": list(nl.vignetting), "gamma": nl.gamma,
           "led_gains": fit.gains.tolist(), "offset": fit.offset.tolist()}
    if nl.span_rad:
        out["arc_span_rad"] = list(nl.span_rad)
    if spec is not None and spec.led_groups:
        first = len(spec.leds) - sum(g.count for g in spec.led_groups)  # the single LEDs' units come first
        out["led_groups"] = {g.name: {"arc_centre_rad": g.arc_centre_rad + nl.led_azimuth_rad[first + i],
                                      "arc_span_rad": nl.span_rad[first + i]} for i, g in enumerate(spec.led_groups)}
    return out


def _bootstrap(fit: ImageFit, model: ImageModel, r: np.ndarray, sector: np.ndarray, count: int, seed: int,
               leak: bool, taps: list[TapView] = ()) -> dict:
    """5-95 % intervals of each parameter over refits on resampled training sectors (and
    fitted taps, drawn with replacement too)."""
    rng = np.random.default_rng(seed)
    even = np.arange(0, SECTORS, 2)
    samples: dict[str, list] = {}
    for _ in range(count):
        drawn = np.bincount(rng.choice(even, len(even)), minlength=SECTORS)
        weight = drawn[sector].astype(np.float64)
        times = np.bincount(rng.choice(len(taps), len(taps)), minlength=len(taps)) if taps else []
        views = [dataclasses.replace(view, weight=float(n)) for view, n in zip(taps, times)]
        refit = ImageFitter(model, r, weight > 0, weight=weight, leak=leak, taps=views,
                            common_turn=bool(taps)).fit(fit.nl, max_evaluations=300)
        for name, value in _parameters(refit, tie=not taps).items():
            samples.setdefault(name, []).append(np.asarray(value, np.float64))
    return {name: np.apply_along_axis(_interval, 0, np.stack(values)).tolist() for name, values in samples.items()}


def _debiased(fit: ImageFit, model: ImageModel, basis: dict, pixels: list[np.ndarray]) -> ImageFit:
    """The fit with ``noise``: the part of its loss the basis' own Monte Carlo noise
    adds, the mean prediction variance over the fitted pixels (``pixels``: the image's,
    then each tap's, where the no-contact basis' variance stands for the tap's). Grid
    points are compared by loss - noise: a basis rendered with strong absorption and
    scattering is noisier (fewer photons reach most of the membrane), and its raw loss
    ranked a blind sensor's own point last of nine."""
    var = model.prediction_variance(basis["variance"], fit.nl, fit.gains)
    noise = float(np.mean(np.concatenate([var[m & model.inside] for m in pixels])))
    return dataclasses.replace(fit, noise=noise)


def _rank_with_taps(taps, fit: ImageFit, model: ImageModel, basis: dict, r: np.ndarray, train: np.ndarray,
                    effects: Effects, spec, mesh, camera: Camera, film, photons, spp, passes, seed, leak,
                    use_cache) -> dict:
    """A grid point judged by the fitted taps with the LEDs where the spec has them (the
    cheap form of ``_fit_taps``: a sixth of its renders, the same at every point, so the
    losses compare): ``loss``, ``noise`` (``_debiased``), ``converged``, and ``known``
    the changes rendered (by tap index), which the full fit reuses."""
    from scenes import captures

    from . import calibrate_taps as ct

    fitted = np.flatnonzero(captures.split(len(taps.ids)))
    subset = captures.RealTaps(taps.images[fitted], taps.depths[fitted], taps.ref_depth,
                               [taps.ids[i] for i in fitted])
    changes = ct.tap_changes(spec, mesh, camera, effects, film, subset, basis, photons, spp, passes, seed, use_cache,
                             azimuths=False)
    views = [v for v in ct.film_views(subset, changes, r, model.inside, film) if v.pixels.sum() >= captures.MIN_REGION]
    joint = ct.fit_with_taps(model, r, train, views, fit, leak) if views else None
    if joint is not None:
        joint = _debiased(joint, model, basis, [train] + [v.pixels for v in views])
    return {"loss": math.inf if joint is None else joint.loss, "noise": 0.0 if joint is None else joint.noise,
            "converged": joint is not None and joint.converged,
            "known": dict(zip(fitted.tolist(), changes["change"]))}


def _fit_taps(taps, fit: ImageFit, model: ImageModel, basis: dict, r: np.ndarray, train: np.ndarray,
              effects: Effects, spec, mesh, camera: Camera, film, photons, spp, passes, seed, leak, use_cache,
              known: dict | None = None):
    """The fit with taps (``pbr_tactile.calibrate_taps``): (fit, fitted taps' views, the
    report's ``taps`` section). ``known``: zero-azimuth changes already rendered."""
    from scenes import captures

    from . import calibrate_taps as ct

    changes = ct.tap_changes(spec, mesh, camera, effects, film, taps, basis, photons, spp, passes, seed, use_cache,
                             known=known)
    views = ct.film_views(taps, changes, r, model.inside, film)
    seen = [int(v.pixels.sum()) >= captures.MIN_REGION for v in views]
    fitted = captures.split(len(views))
    fit_views = [v for v, f, ok in zip(views, fitted, seen) if f and ok]
    judge_views = [v for v, f, ok in zip(views, fitted, seen) if not f and ok]
    if not fit_views:
        raise ValueError(f"none of the fitted taps ({', '.join(np.asarray(taps.ids)[fitted])}) shows a contact: each "
                         f"differs from the no-contact image in fewer than {captures.MIN_REGION} film pixels by more than "
                         f"{captures.CHANGE_LEVEL:.3f}")
    background_only = fit
    fit = ct.fit_with_taps(model, r, train, fit_views, background_only, leak)
    ids = np.asarray(taps.ids)
    report = {
        "fitted": ids[fitted & np.array(seen)].tolist(), "judged": ids[~fitted & np.array(seen)].tolist(),
        "without_contact": ids[~np.array(seen)].tolist(),
        "split": "alternate taps: even ones fitted with the image's training sectors, odd ones judged; each on its "
                 "contact region (where the real tap differs from the real no-contact image)",
        "heldout": ct.tap_scores(model, fit, judge_views, r), "fit": ct.tap_scores(model, fit, fit_views, r),
        "heldout_before_taps": ct.tap_scores(model, background_only, judge_views, r),
    }
    return fit, fit_views, report


def _fast_path_from_taps(profile: Profile, report: dict, spec, mesh, camera, taps, real) -> Profile:
    """The fast path's LED constants fitted to the taps by its renderer plugin (this
    package imports no other renderer): the profile with them, and the report's
    ``fast_path.taps``."""
    from scenes.generate import renderer_plugin

    table, section = renderer_plugin("phong").calibrate(spec, mesh, camera, profile, taps, real)
    report["fast_path"]["taps"] = section
    return dataclasses.replace(profile, phong={**profile.phong, **table})


def heldout_interval(pred: np.ndarray, real: np.ndarray, pixels: np.ndarray, sector: np.ndarray, seed: int = 0,
                     count: int = 1000) -> list[float]:
    """5-95 % bootstrap interval of the held-out R^2 over the held-out sectors (drawn
    with replacement, each sector's pixels weighted by how often it was drawn)."""
    rng = np.random.default_rng(seed)
    odd = np.arange(1, SECTORS, 2)
    values = []
    for _ in range(count):
        weight = np.bincount(rng.choice(odd, len(odd)), minlength=SECTORS)[sector][pixels].astype(np.float64)
        if not weight.sum() > 0:
            continue  # every drawn sector is empty here (a clipped channel)
        y, p = real[pixels], pred[pixels]
        mean = np.sum(weight * y) / np.sum(weight)
        total = np.sum(weight * (y - mean) ** 2)
        if total > 0:
            values.append(1 - np.sum(weight * (y - p) ** 2) / total)
    return _interval(np.array(values)) if values else [float("nan")] * 2


def _fast_path_background(r, circle, camera: Camera, train, test, clipped, judged: dict, sector, seed: int):
    """The fast path's background term fitted on the training sectors
    (scenes.background_model) and judged like the reference; with the best solid colour
    (each channel's training mean) for comparison. Returns the profile table and the
    report's ``fast_path`` section (with the film-sized ``image``, popped by the caller)."""
    from scenes import background_model

    full = (camera.height, camera.width)
    table = background_model.fit(r, circle, train, full, clipped)
    image = background_model.evaluate(table, circle, r.shape[:2], full).astype(np.float64)
    solid = np.where(test[..., None], [r[..., c][train].mean() for c in range(3)], 0.0)
    channels = list(enumerate("rgb"))
    section = {
        "background_model": (f"{background_model.MODEL}: Legendre polynomials of the image circle's radius to degree "
                              f"{table['radial_degree']} times azimuthal harmonics to {table['harmonics']}, "
                              "least squares per channel on the training sectors, clipped pixels censored"),
        "heldout_r2": {ch: r2(image[..., c], r[..., c], judged[ch]) for c, ch in channels},
        "heldout_r2_interval": {ch: heldout_interval(image[..., c], r[..., c], judged[ch], sector, seed)
                                for c, ch in channels},
        "heldout_mae": {ch: float(np.abs(image[..., c] - r[..., c])[judged[ch]].mean()) for c, ch in channels},
        "solid": {"heldout_r2": {ch: r2(solid[..., c], r[..., c], judged[ch]) for c, ch in channels},
                  "heldout_mae": {ch: float(np.abs(solid[..., c] - r[..., c])[judged[ch]].mean())
                                  for c, ch in channels}},
        "image": image,
    }
    return {**table, "coefficients": table["coefficients"].tolist()}, section


def _uncalibrated(rendered: SensorSpec, model: ImageModel, r, train) -> np.ndarray:
    """The reference with its default effects (``model`` of a basis rendered with them,
    of the LEDs ``rendered``: see ``basis_layout``), its LEDs where the spec has them,
    mapped to the real image by the best affine map per channel on the training pixels
    (what uncalibrated means here)."""
    default = Effects()
    from .render import source_response
    from .scene import led_sources

    response = source_response(led_sources(rendered, default), default)
    linear = model.warped(model.start()) @ response
    out = np.zeros_like(r)
    for c in range(3):
        x, y = linear[..., c][train], r[..., c][train]
        a, b = np.polyfit(x, y, 1)
        out[..., c] = np.clip(a * linear[..., c] + b, 0.0, 1.0)
    return np.where(model.inside[..., None], out, 0.0)
