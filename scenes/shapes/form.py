"""The analytic form of a tube-shaped family, and the guarantees every one of its shapes keeps.

The capsule, thumb and paw families (``scenes.shapes.capsule``, ``.thumb``, ``.paw``) are
each a surface of revolution about the tube's axis, triangulated by
``scenes.shapes.revolve.revolve`` (near-equilateral triangles), and then moved vertex by
vertex by a smooth analytic map (:class:`Form`). Meshes are in the tube frame, metres: the
axis is +z, the membrane is open at one planar boundary loop at ``base_z`` and closed at
the top, its apex on (or near) the +z axis, its normals pointing out. ``Z = z - base_z``
is the height above the base, ``(X, Y, Z)`` a point of the revolved ("canonical") surface
and ``(x, y, z)`` the membrane's point.

Every shape that :func:`check_form` accepts (all of a family's bounds, by construction of
the bounds, and verified by the check itself on the analytic surface) keeps these:

1. its radius of curvature is at least MIN_CONCAVE_RADIUS_M in every concave direction
   and MIN_CONVEX_RADIUS_M in every convex one: a surface offset from it by the GelTip's
   2.5 mm, inwards (the core: it folds where a convex radius is smaller) or outwards (a
   mould: it folds where a concave radius is smaller), does not fold over;
2. it is star-shaped from every point of the axis from ``base_z`` to ``base_z +
   STAR_HEIGHT_M`` (the camera's seat among them: 10 mm above the base by default):
   every ray from such a point meets it at most once, and every section by a plane
   through the axis is a simple curve crossing the axis once, at the top;
3. it stays at least MIN_CORE_CLEARANCE_M from the axis between ``base_z`` and the tip's
   start (``Form.z_c``) and from the point of the axis there above it, so a glass core
   5.5 mm in radius (capped by a hemisphere there) fits under 2.5 mm of elastomer;
4. it is narrower than MAX_WIDTH_M: twice its largest distance from the axis.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Callable

import numpy as np
import trimesh

from ..curvature import FLAT_RADIUS_M
from .params import Parameters
from .revolve import revolve

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

#: Points sampled along a profile's arcs and a body.
ARC_POINTS = 256
_BODY_POINTS = 400
#: The analytic check's grid (azimuths all around, heights per part), its finite-difference
#: steps (rad, metres) and how near the pole it samples (rad).
GRID = (240, 72)
_STEP_RAD = 1e-3
_STEP_M = 1e-5
_POLE_GAP_RAD = 0.03
#: Relative slack of the analytic check against its constants (its own error is ~1e-6).
_SLACK = 1e-6


@dataclass(frozen=True, eq=False)
class Form:
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


def _canonical(form: Form, part: str, theta: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Points (N, 3) of the canonical surface: the body at heights v (metres), or the tip
    at elevations v (rad, 0 where it starts, pi/2 at the pole); azimuths theta (rad)."""
    if part == "body":
        r, z = form.r_body(v), v
    else:
        r, z = form.r_tip * np.cos(v), form.z_c + form.h_tip * np.sin(v)
    return np.stack([r * np.cos(theta), r * np.sin(theta), z], axis=1)


def _profile(form: Form, base_z: float) -> np.ndarray:
    """The canonical surface's (r, z) profile, from the base to the pole, camera frame."""
    z = np.linspace(0.0, form.z_c, _BODY_POINTS + 1)
    phi = np.linspace(0.0, math.pi / 2, ARC_POINTS + 1)[1:]
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
    clearance : metres, least distance to the axis segment from base_z to the tip's start.
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


def form_curvatures(form: Form, grid: tuple[int, int] = GRID) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points, outward normals and principal curvatures of a form's analytic surface.

    Finite differences of the form's map on a grid of the canonical surface's parameters
    (azimuth; height on the body, elevation on the tip), over the sector of azimuths the
    shape's symmetry repeats; the tip's last 0.03 rad at the pole is not sampled (the map
    is smooth there), nor is the seam between body and tip, across which the curvature
    jumps as it does on a capsule.

    grid : (azimuths all around, heights per part).

    Returns
    -------
    points : (N, 3) float64, metres, base-relative (the base at z = 0).
    normals : (N, 3) float64, unit, outward.
    k : (N, 2) float64, 1/m, principal curvatures, k[:, 0] <= k[:, 1], convex positive.
    """
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


def diagnose_form(form: Form, grid: tuple[int, int] = GRID) -> Diagnosis:
    """Measure a form's analytic surface against the module's guarantees (see Diagnosis)."""
    p, n, k = form_curvatures(form, grid)
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


def check_form(parameters: Parameters, build: Callable[[Mapping[str, float]], Form], params: Mapping[str, float],
               where: str = "membrane") -> dict[str, float]:
    """A tube-shaped family's parameters with defaults filled in, checked.

    Parameters
    ----------
    parameters : the family's (``PARAMETERS``).
    build : its form from its filled parameters (the family's ``form``).
    params : name -> number, SI units; missing names take defaults.
    where : names the input in messages (e.g. ``"geltip.toml: membrane.params"``).

    Returns
    -------
    dict name -> float, every parameter of the family.

    Raises
    ------
    ValueError naming the input and what was expected: an unknown parameter, a value that
    is not a finite number (or not whole where it must be), a value outside its bounds,
    or a combination whose surface breaks a guarantee of this module (curvature, star
    shape, core clearance, width; see :func:`diagnose_form`).
    """
    out = parameters.check(params, where)
    # Cross-parameter consistency, measured on the analytic surface itself.
    d = diagnose_form(build(out))
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
        raise ValueError(f"{where}: a {parameters.family!r} membrane with {given}: " + "; ".join(problems))
    return out


def mesh_arguments(parameters: Parameters, build: Callable[[Mapping[str, float]], Form], params: Mapping[str, float],
                   base_z: float, edge: float) -> tuple[dict[str, float], float, float]:
    """A shape mesh's arguments, checked (:func:`check_form`; a finite ``base_z``, metres; an
    ``edge`` in (0, MAX_EDGE_M] metres): (params filled, base_z, edge)."""
    p = check_form(parameters, build, params, "membrane")
    base_z, edge = float(base_z), float(edge)
    if not math.isfinite(base_z):
        raise ValueError(f"base_z must be finite (metres), got {base_z}")
    if not 0 < edge <= MAX_EDGE_M:
        raise ValueError(f"edge must be in (0, {MAX_EDGE_M:g}] m, got {edge:g}"
                         + (" (millimetres? metres were expected)" if edge > MAX_EDGE_M else ""))
    return p, base_z, edge


def warped_mesh(form: Form, base_z: float, edge: float) -> trimesh.Trimesh:
    """A form's membrane in the tube frame: its canonical surface revolved with triangles of
    edge about ``edge`` (metres) from its open base at ``base_z``, each vertex moved by
    the form's map."""
    mesh = revolve(_profile(form, base_z), edge)
    V = np.asarray(mesh.vertices) - [0.0, 0.0, base_z]
    moved = form.warp(V)
    moved[:, 2] += base_z
    return trimesh.Trimesh(moved, mesh.faces, process=False)
