"""Parametric membrane shapes: the capsule, thumb and paw families, generated from a few numbers.

Every family is a surface of revolution about the tube's axis, triangulated by
``scenes.geometry.revolve`` (near-equilateral triangles), and then moved vertex by
vertex by a smooth analytic map. Meshes are in the tube frame, metres: the axis is +z,
the membrane is open at one planar boundary loop at ``base_z`` and closed at the top,
its apex on (or near) the +z axis, its normals pointing out.

Below, ``Z = z - base_z`` is the height above the base, ``(X, Y, Z)`` a point of the
revolved ("canonical") surface and ``(x, y, z)`` the membrane's point.

- ``capsule``: a cylinder closed by a hemisphere, exactly
  ``scenes.geometry.capsule_mesh``'s mesh (no map).
- ``thumb``: a flattened, leaning fingertip. The canonical surface is a cylinder of
  radius ``R0`` up to ``Z_c = length - tip_height``, closed by a half spheroid of
  semi-axes ``(R0, R0, tip_height)``; ``R0`` is the mean radius of the cross-section
  below, so that the map keeps edge lengths near ``edge`` on average. The map is::

      x = a X / R0                                   a = width / 2
      y = b psi(Y / R0) - tip_lean * t**3           b = depth / 2
      z = base_z + Z                                 t = max(0, (Z - Z_c) / tip_height)
      psi(v) = v                        (v >= 0, the back: a half ellipse)
      psi(v) = v + f v**3 (1 + v)       (v < 0, the pad, on -y; f = pad_flatness)

  The cross-section is an ellipse, wider (x) than deep (y), whose -y half (the pad) is
  flattened: its curvature at the pad's centre is ``1 - pad_flatness`` times the back's.
  ``psi`` is C2 (its third derivative jumps at v = 0) and increasing, as ``t**3`` is C2
  at the tip's start. The tip is a half spheroid lower than the cross-section is wide
  (``tip_height <= width / 2``), sheared towards the pad: the apex sits at ``(0,
  -tip_lean, base_z + length)``, and the +z axis leaves the membrane just behind it.
  (In the camera frame, x right and y down, the pad faces the image's top.)
- ``paw``: a waisted capsule whose tip carries ``toes`` convex bumps with saddle-shaped
  valleys between them. The canonical surface revolves ``r(Z) = radius - waist_depth *
  B((Z - Z_w) / h_w)`` (``Z_w = WAIST_CENTRE * cylinder_length``, ``h_w =
  WAIST_HALF_LENGTH * cylinder_length``) up to ``Z_c = cylinder_length``, closed by a
  hemisphere of ``radius`` about ``c = (0, 0, Z_c)``. The map leaves the body as it is and
  moves each tip point ``c + radius u`` (``u`` unit) along ``u``::

      p = c + (radius + H(u)) u,   H(u) = toe_height * sum_k B(|u - d_k| / (2 sin(w / 2)))
      B(s) = (1 - s**2)**3 for |s| < 1, else 0            (C2, a smooth bump)
      d_k = (sin s_t cos(2 pi k / n), sin s_t sin(2 pi k / n), cos s_t)

  with ``n = toes``, ``s_t = toe_spread`` the toes' angle from the axis and ``w`` each
  toe's angular half-width: ``TOE_WIDTH_PER_GAP`` times the angle between neighbouring
  toes (so neighbours overlap into saddles), at most ``TOE_REACH_RAD - toe_spread`` (so
  no toe reaches the tip's start, where the map is the identity).

Every shape that :func:`check_params` accepts (all of BOUNDS, by construction of the
bounds, and verified by the check itself on the analytic surface) keeps these:

1. its radius of curvature is at least MIN_CONCAVE_RADIUS_M in every concave direction
   and MIN_CONVEX_RADIUS_M in every convex one: a surface offset from it by the GelTip's
   2.5 mm, inwards (the core: it folds where a convex radius is smaller) or outwards (a
   mould: it folds where a concave radius is smaller), does not fold over;
2. it is star-shaped from every point of the axis from ``base_z`` to ``base_z +
   STAR_HEIGHT_M`` (the camera's seat among them: 10 mm above the base by default):
   every ray from such a point meets it at most once, and every section by a plane
   through the axis is a simple curve crossing the axis once, at the top;
3. it stays at least MIN_CORE_CLEARANCE_M from the axis between ``base_z`` and
   :func:`tip_start_z` and from the point of the axis at :func:`tip_start_z` above it,
   so a glass core 5.5 mm in radius (capped by a hemisphere there) fits under 2.5 mm of
   elastomer;
4. it is narrower than MAX_WIDTH_M: twice its largest distance from the axis.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Callable

import numpy as np
import trimesh

from .curvature import FLAT_RADIUS_M
from .geometry import capsule_profile, revolve

FAMILIES = ("capsule", "thumb", "paw")

#: Smallest radius of curvature in any concave direction (where the membrane curves
#: away from its outward normal, e.g. across a valley), metres.
MIN_CONCAVE_RADIUS_M = 4.0e-3
#: Smallest radius of curvature in any convex direction, metres: above the GelTip's
#: 2.5 mm elastomer, so the core offset inwards from a bump does not fold over.
MIN_CONVEX_RADIUS_M = 3.0e-3
#: Least distance from the membrane to the axis below the tip's start, and to the axis'
#: point there above it, metres: 2.5 mm of elastomer over a core 5.5 mm in radius.
MIN_CORE_CLEARANCE_M = 8.0e-3
#: Largest width, metres: twice the largest distance of the membrane from the axis.
MAX_WIDTH_M = 40.0e-3
#: The membrane is star-shaped from every point of the axis from base_z to this high
#: above it, metres (the GelTip's camera sits 10 mm above its base).
STAR_HEIGHT_M = 12.0e-3
#: Least cosine between the outward normal and the ray from those points: a margin that
#: keeps rays from grazing the membrane (87 degrees at most).
STAR_MIN_COSINE = 0.05
#: Largest mesh edge, metres: a coarser mesh does not follow the toes and the tip.
MAX_EDGE_M = 4.0e-3

#: The paw's waist: its centre and half-length as shares of cylinder_length.
WAIST_CENTRE = 0.55
WAIST_HALF_LENGTH = 0.35
#: The paw's toe half-width as a share of the angle between neighbouring toes (> 1/2:
#: neighbours overlap, leaving a saddle between them).
TOE_WIDTH_PER_GAP = 0.8
#: Largest angle from the axis a toe reaches, rad (below pi/2: the toes stay on the tip).
TOE_REACH_RAD = 1.4

DEFAULTS: dict[str, dict[str, float]] = {
    "capsule": {
        #: m, radius of the cylinder and of its hemispherical tip
        "radius": 0.0115,
        #: m, length of the cylinder, from the base to the tip's centre
        "cylinder_length": 0.044,
    },
    "thumb": {
        #: m, width across x (the elliptical cross-section's major axis)
        "width": 0.023,
        #: m, depth across y, from the pad (-y) to the back (+y)
        "depth": 0.018,
        #: m, length from the base to the apex
        "length": 0.050,
        #: m, height of the tip (a flattened half spheroid) above where it starts
        "tip_height": 0.0095,
        #: -, flattening of the pad (-y): 0 an ellipse, 1 flat at the pad's centre
        "pad_flatness": 0.5,
        #: m, shift of the apex towards the pad (-y)
        "tip_lean": 0.0015,
    },
    "paw": {
        #: m, radius of the body and of the hemispherical tip under the toes
        "radius": 0.0115,
        #: m, length of the body, from the base to the tip's centre
        "cylinder_length": 0.040,
        #: -, number of toes on the tip (a whole number)
        "toes": 4.0,
        #: m, height of each toe above the hemisphere
        "toe_height": 0.0012,
        #: rad, angle of the toes' centres from the axis, seen from the tip's centre
        "toe_spread": 0.6,
        #: m, depth of the waist (neck) around the body's middle
        "waist_depth": 0.001,
    },
}

BOUNDS: dict[str, dict[str, tuple[float, float]]] = {
    "capsule": {
        "radius": (0.008, 0.0195),  # m: the core clearance; the width limit
        "cylinder_length": (0.005, 0.070),  # m: star-shaped from STAR_HEIGHT_M
    },
    "thumb": {
        "width": (0.021, 0.030),  # m: wider than deep by 15 % at least
        "depth": (0.016, 0.018),  # m: the core clearance
        "length": (0.035, 0.065),  # m
        "tip_height": (0.009, 0.0105),  # m: the core clearance; flatter than wide
        "pad_flatness": (0.0, 0.8),  # -: the pad shoulders' convex radius
        "tip_lean": (0.0, 0.002),  # m: the core clearance behind the tip
    },
    "paw": {
        "radius": (0.0095, 0.013),  # m: the core clearance at the waist
        "cylinder_length": (0.030, 0.050),  # m: star-shaped past the waist
        "toes": (3.0, 5.0),  # -: more toes are narrower: 6 curve too tightly at the highest toe_height
        "toe_height": (0.0, 0.0012),  # m: the toes' convex and the valleys' concave radii
        "toe_spread": (0.6, 0.8),  # rad: the toes' convex radius (their width shrinks nearer the axis)
        "waist_depth": (0.0, 0.0015),  # m: the core clearance; star-shaped
    },
}

#: Each parameter's unit: "m", "rad" or "-" (dimensionless).
UNITS: dict[str, dict[str, str]] = {
    "capsule": {"radius": "m", "cylinder_length": "m"},
    "thumb": {"width": "m", "depth": "m", "length": "m", "tip_height": "m", "pad_flatness": "-", "tip_lean": "m"},
    "paw": {"radius": "m", "cylinder_length": "m", "toes": "-", "toe_height": "m", "toe_spread": "rad",
            "waist_depth": "m"},
}

#: How messages name each unit.
_UNIT_WORDS = {"m": "metres", "rad": "radians", "-": "dimensionless"}
_UNIT_SUFFIX = {"m": " m", "rad": " rad", "-": ""}
#: Parameters that must be whole numbers.
_WHOLE = {("paw", "toes")}
#: Points sampled along a profile's arcs and the paw's body.
_ARC_POINTS = 256
_BODY_POINTS = 400
#: The analytic check's grid (azimuths, heights per part), its finite-difference steps
#: (rad, metres) and how near the pole it samples (rad).
_GRID = (240, 72)
_STEP_RAD = 1e-3
_STEP_M = 1e-5
_POLE_GAP_RAD = 0.03
#: Relative slack of the analytic check against its constants (its own error is ~1e-6).
_SLACK = 1e-6


@dataclass(frozen=True, eq=False)
class _Form:
    """A family's canonical surface of revolution and its map, base-relative (Z = z - base_z).

    r_body : (N,) Z -> (N,) body radius, metres, for 0 <= Z <= z_c.
    z_c : where the body ends and the tip starts, metres above the base.
    r_tip, h_tip : the tip's half spheroid: radial and axial semi-axes, metres.
    warp : (N, 3) canonical points -> (N, 3) membrane points, base-relative, metres.
    sector : (start, stop) rad, azimuths whose surface the shape's symmetry repeats all
        around (what the analytic check samples).
    """

    r_body: Callable[[np.ndarray], np.ndarray]
    z_c: float
    r_tip: float
    h_tip: float
    warp: Callable[[np.ndarray], np.ndarray]
    sector: tuple[float, float] = (0.0, 2 * math.pi)


def _bump(s2: np.ndarray) -> np.ndarray:
    """B as a function of s**2: (1 - s**2)**3 inside the unit disc, 0 outside (C2)."""
    return np.where(s2 < 1.0, (1.0 - np.minimum(s2, 1.0)) ** 3, 0.0)


def _pad(v: np.ndarray, flatness: float) -> np.ndarray:
    """psi(v): the back (v >= 0) as it is, the pad (v < 0) flattened, monotone on [-1, 1]."""
    return np.where(v < 0, v + flatness * v**3 * (1.0 + v), v)


def _thumb(p: Mapping[str, float]) -> _Form:
    a, b = p["width"] / 2, p["depth"] / 2
    f, h, lean = p["pad_flatness"], p["tip_height"], p["tip_lean"]
    z_c = p["length"] - h
    t = np.linspace(0.0, 2 * math.pi, 2049)
    section = np.stack([a * np.cos(t), b * _pad(np.sin(t), f)], axis=1)
    r0 = float(np.linalg.norm(np.diff(section, axis=0), axis=1).sum()) / (2 * math.pi)

    def warp(q: np.ndarray) -> np.ndarray:
        tip = np.clip((q[:, 2] - z_c) / h, 0.0, None)
        return np.stack([a * q[:, 0] / r0, b * _pad(q[:, 1] / r0, f) - lean * tip**3, q[:, 2]], axis=1)

    # Mirror-symmetric about x = 0: the half x >= 0 is the whole.
    return _Form(lambda z: np.full(np.shape(z), r0), z_c, r0, h, warp, (-math.pi / 2, math.pi / 2))


def toe_directions(params: Mapping[str, float]) -> tuple[np.ndarray, float]:
    """The paw's toe centres and half-width.

    Parameters
    ----------
    params : the paw's parameters (filled and checked by :func:`check_params`).

    Returns
    -------
    d : (toes, 3) float64, unit directions of the toes' centres from the tip's centre.
    w : float, rad, each toe's angular half-width.
    """
    n, spread = int(round(params["toes"])), params["toe_spread"]
    azimuth = 2 * math.pi * np.arange(n) / n
    d = np.stack([math.sin(spread) * np.cos(azimuth), math.sin(spread) * np.sin(azimuth),
                  np.full(n, math.cos(spread))], axis=1)
    gap = 2 * math.asin(math.sin(spread) * math.sin(math.pi / n))
    return d, min(TOE_WIDTH_PER_GAP * gap, TOE_REACH_RAD - spread)


def _paw(p: Mapping[str, float]) -> _Form:
    radius, z_c, depth, height = p["radius"], p["cylinder_length"], p["waist_depth"], p["toe_height"]
    z_w, h_w = WAIST_CENTRE * z_c, WAIST_HALF_LENGTH * z_c
    d, w = toe_directions(p)
    # |u - d|^2 = 2 - 2 u.d for unit u, d; B's argument is that over the chord of w.
    chord2 = (2 * math.sin(w / 2)) ** 2
    centre = np.array([0.0, 0.0, z_c])

    def r_body(z: np.ndarray) -> np.ndarray:
        return radius - depth * _bump(((np.asarray(z) - z_w) / h_w) ** 2)

    def warp(q: np.ndarray) -> np.ndarray:
        out = np.array(q, dtype=np.float64)
        tip = q[:, 2] > z_c
        rel = q[tip] - centre
        u = rel / np.linalg.norm(rel, axis=1, keepdims=True)
        lift = height * _bump((2.0 - 2.0 * u @ d.T) / chord2).sum(axis=1)
        out[tip] = centre + rel * (1.0 + lift / radius)[:, None]
        return out

    # n-fold and mirror-symmetric about the first toe's azimuth.
    return _Form(r_body, z_c, radius, radius, warp, (0.0, math.pi / len(d)))


def _capsule(p: Mapping[str, float]) -> _Form:
    radius = p["radius"]
    return _Form(lambda z: np.full(np.shape(z), radius), p["cylinder_length"], radius, radius, lambda q: q,
                 (0.0, 4 * 2 * math.pi / _GRID[0]))


_FORMS = {"capsule": _capsule, "thumb": _thumb, "paw": _paw}


def _canonical(form: _Form, part: str, theta: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Points (N, 3) of the canonical surface: the body at heights v (metres), or the tip
    at elevations v (rad, 0 where it starts, pi/2 at the pole); azimuths theta (rad)."""
    if part == "body":
        r, z = form.r_body(v), v
    else:
        r, z = form.r_tip * np.cos(v), form.z_c + form.h_tip * np.sin(v)
    return np.stack([r * np.cos(theta), r * np.sin(theta), z], axis=1)


def _profile(form: _Form, base_z: float) -> np.ndarray:
    """The canonical surface's (r, z) profile, from the base to the pole, camera frame."""
    z = np.linspace(0.0, form.z_c, _BODY_POINTS + 1)
    phi = np.linspace(0.0, math.pi / 2, _ARC_POINTS + 1)[1:]
    r = np.concatenate([form.r_body(z), form.r_tip * np.cos(phi)])
    pts = np.stack([r, np.concatenate([z, form.z_c + form.h_tip * np.sin(phi)]) + base_z], axis=1)
    pts[-1, 0] = 0.0
    return pts


@dataclass(frozen=True)
class Diagnosis:
    """What the analytic check measured on a shape's surface (finite differences of its
    map on a grid of its parameters; the pole's last 0.03 rad unsampled).

    min_concave_radius : metres, smallest radius of curvature in a concave direction
        (inf when none is concave).
    min_convex_radius : metres, smallest radius of curvature in a convex direction.
    star_cosine : least cosine between the outward normal and the ray to the point from
        the axis at base_z and at base_z + STAR_HEIGHT_M (the whole segment between is at
        least as good: the test is linear in the ray's origin).
    clearance : metres, least distance to the axis segment from base_z to tip_start_z.
    width : metres, twice the largest distance from the axis.
    saddle_share : share of the sampled points with one principal curvature of each sign
        beyond 1 / ``scenes.curvature.FLAT_RADIUS_M``: the concave regions' (saddles') extent.
    """

    min_concave_radius: float
    min_convex_radius: float
    star_cosine: float
    clearance: float
    width: float
    saddle_share: float


def principal_curvatures(family: str, params: Mapping[str, float],
                         grid: tuple[int, int] = _GRID) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points, outward normals and principal curvatures of a shape's analytic surface.

    Finite differences of the family's map on a grid of the canonical surface's
    parameters (azimuth; height on the body, elevation on the tip), over the sector of
    azimuths the shape's symmetry repeats; the tip's last 0.03 rad at the pole is not
    sampled (the map is smooth there), nor is the seam between body and tip, across
    which the curvature jumps as it does on a capsule.

    Parameters
    ----------
    family : one of FAMILIES.
    params : the family's parameters; defaults are filled in, names and numbers are
        checked but not BOUNDS, so that shapes beyond them can be measured.
    grid : (azimuths all around, heights per part).

    Returns
    -------
    points : (N, 3) float64, metres, base-relative (the base at z = 0).
    normals : (N, 3) float64, unit, outward.
    k : (N, 2) float64, 1/m, principal curvatures, k[:, 0] <= k[:, 1], convex positive.
    """
    family = _family(family, "membrane")
    return _curvatures(_FORMS[family](_fill(family, params, "membrane")), grid)


def _curvatures(form: _Form, grid: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """principal_curvatures of a form."""
    n_theta, n_v = grid
    out = []
    for part, step, lo, hi in (("body", _STEP_M, 0.0, form.z_c), ("tip", _STEP_RAD, 0.0, math.pi / 2 - _POLE_GAP_RAD)):
        if hi - lo < 4 * step:
            continue
        a0, a1 = form.sector
        azimuths = np.linspace(a0, a1, max(2, int(round(n_theta * (a1 - a0) / (2 * math.pi)))) + 1)
        theta, v = np.meshgrid(azimuths, np.linspace(lo + 2 * step, hi - 2 * step, n_v))
        theta, v = theta.ravel(), v.ravel()
        h = _STEP_RAD
        # The 3 x 3 stencil of (azimuth, height) offsets, mapped in one call.
        offsets = [(i, j) for i in (-1, 0, 1) for j in (-1, 0, 1)]
        q = np.concatenate([_canonical(form, part, theta + i * h, v + j * step) for i, j in offsets])
        s = dict(zip(offsets, np.split(form.warp(q), len(offsets))))
        p = s[0, 0]
        su, sv = (s[1, 0] - s[-1, 0]) / (2 * h), (s[0, 1] - s[0, -1]) / (2 * step)
        suu = (s[1, 0] - 2 * p + s[-1, 0]) / h**2
        svv = (s[0, 1] - 2 * p + s[0, -1]) / step**2
        suv = (s[1, 1] - s[1, -1] - s[-1, 1] + s[-1, -1]) / (4 * h * step)
        n = np.cross(su, sv)
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        E, F, G = (su * su).sum(1), (su * sv).sum(1), (sv * sv).sum(1)
        L, M, N = -(suu * n).sum(1), -(suv * n).sum(1), -(svv * n).sum(1)
        det = E * G - F**2
        K = (L * N - M**2) / det
        H = (E * N - 2 * F * M + G * L) / (2 * det)
        disc = np.sqrt(np.maximum(H**2 - K, 0.0))
        out.append((p, n, np.stack([H - disc, H + disc], axis=1)))
    return tuple(np.concatenate(a) for a in zip(*out))


def diagnose(family: str, params: Mapping[str, float], grid: tuple[int, int] = _GRID) -> Diagnosis:
    """Measure a shape's analytic surface against the module's guarantees (see Diagnosis).

    ``params`` are filled with defaults and checked against BOUNDS' names and types,
    not their ranges or the guarantees (this is what :func:`check_params` uses to
    enforce them).
    """
    family = _family(family, "membrane")
    form = _FORMS[family](_fill(family, params, "membrane"))
    p, n, k = _curvatures(form, grid)
    concave = -k[:, 0].min()
    star = np.inf
    for c in (0.0, STAR_HEIGHT_M):
        ray = p - np.array([0.0, 0.0, c])
        star = min(star, float(((ray * n).sum(1) / np.linalg.norm(ray, axis=1)).min()))
    r = np.linalg.norm(p[:, :2], axis=1)
    above = np.maximum(p[:, 2] - form.z_c, 0.0)
    clearance = float(np.sqrt(r**2 + above**2).min())
    saddle = float(np.mean((k[:, 0] < -1 / FLAT_RADIUS_M) & (k[:, 1] > 1 / FLAT_RADIUS_M)))
    return Diagnosis(min_concave_radius=float(1 / concave) if concave > 0 else math.inf,
                     min_convex_radius=float(1 / k[:, 1].max()), star_cosine=star, clearance=clearance,
                     width=float(2 * r.max()), saddle_share=saddle)


def _family(family, where: str) -> str:
    if not isinstance(family, str) or family not in FAMILIES:
        raise ValueError(f"{where}: unknown shape family {family!r}; expected one of {', '.join(FAMILIES)}")
    return family


def _fill(family: str, params: Mapping[str, float], where: str) -> dict[str, float]:
    """Defaults filled in; names known and values finite numbers (whole where needed)."""
    if not isinstance(params, Mapping):
        raise ValueError(f"{where}: parameters must be a mapping of name to number, got {type(params).__name__}")
    known = DEFAULTS[family]
    out = dict(known)
    for name, value in params.items():
        if name not in known:
            raise ValueError(f"{where}: unknown parameter {name!r} for a {family!r} membrane; expected some of "
                             f"{', '.join(known)}")
        what = _UNIT_WORDS[UNITS[family][name]]
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
            raise ValueError(f"{where}.{name} must be a number ({what}), got {value!r}")
        value = float(value)
        if not math.isfinite(value):
            raise ValueError(f"{where}.{name} must be finite ({what}), got {value}")
        if (family, name) in _WHOLE and value != round(value):
            raise ValueError(f"{where}.{name} must be a whole number, got {value}")
        out[name] = value
    return out


def check_params(family: str, params: Mapping[str, float], where: str = "membrane") -> dict[str, float]:
    """A shape family's parameters with defaults filled in, checked.

    Parameters
    ----------
    family : one of FAMILIES.
    params : name -> number, SI units (see DEFAULTS, UNITS); missing names take defaults.
    where : names the input in messages (e.g. ``"geltip.toml: membrane.params"``).

    Returns
    -------
    dict name -> float, every parameter of the family.

    Raises
    ------
    ValueError naming the input and what was expected: an unknown family or parameter,
    a value that is not a finite number (or not whole, for ``toes``), a value outside
    BOUNDS, or a combination whose surface breaks a guarantee of this module (curvature,
    star shape, core clearance, width; see :func:`diagnose`).
    """
    family = _family(family, where)
    out = _fill(family, params, where)
    for name, (lo, hi) in BOUNDS[family].items():
        if not lo <= out[name] <= hi:
            unit = _UNIT_SUFFIX[UNITS[family][name]]
            raise ValueError(f"{where}.{name} = {out[name]:g}{unit} is outside its bounds [{lo:g}, {hi:g}]{unit} "
                             f"({_UNIT_WORDS[UNITS[family][name]]}) for a {family!r} membrane")
    # Cross-parameter consistency, measured on the analytic surface itself.
    d = diagnose(family, out)
    given = ", ".join(f"{k}={v:g}" for k, v in out.items())
    problems = []
    if d.min_concave_radius < MIN_CONCAVE_RADIUS_M * (1 - _SLACK):
        problems.append(f"its smallest concave radius of curvature is {d.min_concave_radius * 1e3:.3g} mm, "
                        f"under MIN_CONCAVE_RADIUS_M = {MIN_CONCAVE_RADIUS_M * 1e3:g} mm")
    if d.min_convex_radius < MIN_CONVEX_RADIUS_M * (1 - _SLACK):
        problems.append(f"its smallest convex radius of curvature is {d.min_convex_radius * 1e3:.3g} mm, "
                        f"under MIN_CONVEX_RADIUS_M = {MIN_CONVEX_RADIUS_M * 1e3:g} mm")
    if d.star_cosine < STAR_MIN_COSINE:
        problems.append(f"it is not star-shaped from the axis up to STAR_HEIGHT_M = {STAR_HEIGHT_M * 1e3:g} mm "
                        f"above its base (a ray meets it at cosine {d.star_cosine:.3g} < {STAR_MIN_COSINE:g})")
    if d.clearance < MIN_CORE_CLEARANCE_M * (1 - _SLACK):
        problems.append(f"it comes {d.clearance * 1e3:.3g} mm from the core's axis, under "
                        f"MIN_CORE_CLEARANCE_M = {MIN_CORE_CLEARANCE_M * 1e3:g} mm")
    if d.width >= MAX_WIDTH_M:
        problems.append(f"it is {d.width * 1e3:.3g} mm wide, not under MAX_WIDTH_M = {MAX_WIDTH_M * 1e3:g} mm")
    if problems:
        raise ValueError(f"{where}: a {family!r} membrane with {given}: " + "; ".join(problems))
    return out


def tip_start_z(family: str, params: Mapping[str, float], base_z: float) -> float:
    """Where the family's body ends and its tip starts, metres (camera frame): the top of
    the axis segment the membrane keeps MIN_CORE_CLEARANCE_M from."""
    family = _family(family, "membrane")
    return float(base_z) + _FORMS[family](_fill(family, params, "membrane")).z_c


def shape_mesh(family: str, params: Mapping[str, float], base_z: float, edge: float) -> trimesh.Trimesh:
    """The outer membrane surface of a shape family, in the tube frame.

    Parameters
    ----------
    family : one of FAMILIES.
    params : name -> number, SI units; checked by :func:`check_params`.
    base_z : float, metres, height of the open base (the tube's axis is +z).
    edge : float, metres, target triangle edge length, in (0, MAX_EDGE_M].

    Returns
    -------
    trimesh.Trimesh, metres: one manifold sheet with outward normals, open at one planar
    boundary loop at z = base_z, closed at the top; near-equilateral triangles of edge
    about ``edge``. The capsule's is ``scenes.geometry.capsule_mesh``'s exactly.
    """
    p = check_params(family, params, "membrane")
    base_z, edge = float(base_z), float(edge)
    if not math.isfinite(base_z):
        raise ValueError(f"base_z must be finite (metres), got {base_z}")
    if not 0 < edge <= MAX_EDGE_M:
        raise ValueError(f"edge must be in (0, {MAX_EDGE_M:g}] m, got {edge:g}"
                         + (" (millimetres? metres were expected)" if edge > MAX_EDGE_M else ""))
    if family == "capsule":
        return revolve(capsule_profile(p["radius"], p["cylinder_length"], base_z), edge)
    form = _FORMS[family](p)
    mesh = revolve(_profile(form, base_z), edge)
    V = np.asarray(mesh.vertices) - [0.0, 0.0, base_z]
    moved = form.warp(V)
    moved[:, 2] += base_z
    return trimesh.Trimesh(moved, mesh.faces, process=False)
