"""The pad family: a flat sensor's domed elastomer pad on a clear plate, as a flat GelSight's.

A pad is an open sheet, not a tube: the painted outer surface of an elastomer disc of
``radius`` whose top is a spherical cap of radius of curvature ``dome_radius`` (a real
pad is seldom flat: the public GelSight's gel map is such a cap, 50 mm in radius), seen
from below by a camera on its axis. Its one boundary loop, the disc's rim, is the
membrane's base (``scenes.shapes.mesh.base_loop``) and lies in the plane z = ``base_z``;
the apex sits :func:`sag` above it, on the +z axis. The elastomer under it is
``thickness`` thick (``scenes.body`` offsets the sheet inwards, along its normals), and
the clear plate that carries it is the body's glass, ``glass_wall`` thick
(``membrane.glass_ior``: acrylic's 1.49 for a GelSight's plate): everything that reads a
body (the elastic layer, the protocols' safe depth, the MuJoCo rig, the reference's
elastomer solid and glass) takes a pad as it takes a tube. Its gel reaches past the
camera's view, to the LEDs at its edge: the camera must see gel in every pixel
(:data:`FILLS_VIEW`).

Meshes are in the tube frame, metres: the axis is +z, normals point out of the elastomer
(+z at the apex), near-equilateral triangles of edge about ``edge``
(``scenes.shapes.revolve`` of the cap's profile).
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
import trimesh

from .interface import centre_and_rim, derived_core
from .params import Parameters
from .revolve import revolve

NAME = "pad"
TABLE_KEYS: tuple[str, ...] = ()
SIZE_FROM = "[membrane.params]"
CORE_FROM = "thickness"
SEATED = True
FILLS_VIEW = True
PUBLISHED = False
REGIONS = ("centre", "rim")

DEFAULTS: dict[str, float] = {
    #: m, radius of the pad's rim (the disc the camera looks up at)
    "radius": 0.013,
    #: m, radius of curvature of its domed top (a spherical cap)
    "dome_radius": 0.050,
}

BOUNDS: dict[str, tuple[float, float]] = {
    "radius": (0.003, 0.040),  # m: a fingertip's pad to a palm's
    "dome_radius": (0.005, 1.0),  # m: any cap below a hemisphere of the pad (checked), nearly flat at 1 m
}

#: Each parameter's unit.
UNITS: dict[str, str] = {"radius": "m", "dome_radius": "m"}

PARAMETERS = Parameters(NAME, DEFAULTS, BOUNDS, UNITS)

#: The cap must stay this far below a hemisphere: its rim's slope, rad, at most (a steeper
#: rim would put the sheet's edge almost along the camera's rays).
MAX_RIM_SLOPE_RAD = math.radians(60.0)
#: Points along the cap's profile.
_PROFILE_POINTS = 256


def check_params(params: Mapping[str, float], where: str = "membrane.params") -> dict[str, float]:
    """A pad's parameters with defaults filled in, checked: known names, finite numbers
    within BOUNDS, and a cap no steeper at its rim than MAX_RIM_SLOPE_RAD. ValueError
    naming ``where`` and what was expected otherwise."""
    out = PARAMETERS.check(params, where)
    slope = rim_slope(out)
    if slope > MAX_RIM_SLOPE_RAD:
        raise ValueError(f"{where}: a {NAME!r} membrane of radius {out['radius'] * 1e3:g} mm under a dome of radius "
                         f"{out['dome_radius'] * 1e3:g} mm slopes {math.degrees(slope):.0f} deg at its rim, over "
                         f"{math.degrees(MAX_RIM_SLOPE_RAD):.0f} deg: give a larger dome_radius or a smaller radius")
    return out


def rim_slope(params: Mapping[str, float]) -> float:
    """The cap's slope at its rim, rad: asin(radius / dome_radius)."""
    return math.asin(min(params["radius"] / params["dome_radius"], 1.0))


def sag(params: Mapping[str, float]) -> float:
    """How far the apex stands above the rim's plane, metres: R - sqrt(R^2 - rho^2)."""
    R, rho = params["dome_radius"], params["radius"]
    return R - math.sqrt(R * R - rho * rho)


def profile(params: Mapping[str, float], base_z: float) -> np.ndarray:
    """(K, 2) the cap's (r, z) profile from the rim (z = base_z) to the apex (r = 0), metres."""
    R, rho = params["dome_radius"], params["radius"]
    centre_z = base_z + sag(params) - R
    phi = np.linspace(math.asin(rho / R), 0.0, _PROFILE_POINTS + 1)
    pts = np.stack([R * np.sin(phi), centre_z + R * np.cos(phi)], axis=1)
    pts[0] = (rho, base_z)
    pts[-1, 0] = 0.0
    return pts


def shape_mesh(params: Mapping[str, float], base_z: float, edge: float) -> trimesh.Trimesh:
    """The pad's outer surface in the tube frame (module doc).

    Parameters
    ----------
    params : name -> number, metres (DEFAULTS); checked by :func:`check_params`.
    base_z : float, metres, the rim's plane.
    edge : float, metres, target triangle edge, in (0, radius / 4].

    Returns
    -------
    trimesh.Trimesh, metres: one manifold sheet, normals out of the elastomer, open at its
    rim alone.
    """
    p = check_params(params)
    base_z, edge = float(base_z), float(edge)
    if not math.isfinite(base_z):
        raise ValueError(f"base_z must be finite (metres), got {base_z}")
    if not 0 < edge <= p["radius"] / 4:
        raise ValueError(f"edge must be in (0, {p['radius'] / 4:g}] m (a quarter of the pad's radius), got {edge:g}")
    return revolve(profile(p, base_z), edge)


# The family's interface (``scenes.shapes.interface``): its core is derived.
membrane_params, check, tube, mesh = derived_core(check_params, shape_mesh)


def regions(membrane, points: np.ndarray, inside: np.ndarray) -> dict[str, np.ndarray]:
    """The pad's centre, nearest the camera's axis, and its rim."""
    return centre_and_rim(points, inside)
