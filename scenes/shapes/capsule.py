"""The capsule family: a cylinder closed by a hemisphere over a round glass tube, the published GelTip.

A spec sizes a capsule with its [membrane] table's own keys (:data:`TABLE_KEYS`):
``radius`` (the membrane's, and its tip's), ``cylinder_length`` (from the base to the
tip's centre) and ``core_radius`` (the glass tube's outer radius). The elastomer between
is ``radius - core_radius`` thick everywhere, so its body is known in closed form
(:func:`tube`) and no core is derived. Its mesh revolves :func:`profile` about the tube's
axis (``scenes.shapes.revolve``); as a form of ``scenes.shapes.form`` (no map: the
surface of revolution itself) it keeps that module's guarantees within :data:`BOUNDS`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
import trimesh

from .interface import Tube, no_params, tip_and_body
from .form import ARC_POINTS, GRID, Form, check_form, mesh_arguments
from .params import Parameters
from .revolve import revolve

NAME = "capsule"
TABLE_KEYS = ("radius", "cylinder_length", "core_radius")
SIZE_FROM = "radius and cylinder_length"
CORE_FROM = "core_radius"
SEATED = True
FILLS_VIEW = False
PUBLISHED = True
REGIONS = ("tip", "body")

DEFAULTS: dict[str, float] = {
    #: m, radius of the cylinder and of its hemispherical tip
    "radius": 0.0115,
    #: m, length of the cylinder, from the base to the tip's centre
    "cylinder_length": 0.044,
}

BOUNDS: dict[str, tuple[float, float]] = {
    "radius": (0.008, 0.0195),  # m: the core clearance; the width limit
    "cylinder_length": (0.005, 0.070),  # m: star-shaped from STAR_HEIGHT_M
}

#: Each parameter's unit: "m", "rad" or "-" (dimensionless).
UNITS: dict[str, str] = {"radius": "m", "cylinder_length": "m"}

PARAMETERS = Parameters(NAME, DEFAULTS, BOUNDS, UNITS)


def profile(radius: float, cylinder_length: float, base_z: float) -> np.ndarray:
    """Profile of a cylinder closed by a hemisphere, as a dense (r, z) polyline.

    Returns
    -------
    (K, 2) float64, metres: r >= 0 and z, from the open base to the pole (r = 0).
    """
    z_top = base_z + cylinder_length
    theta = np.linspace(0.0, math.pi / 2, ARC_POINTS + 1)
    arc = np.stack([radius * np.cos(theta), z_top + radius * np.sin(theta)], axis=1)
    base = np.array([[radius, base_z]])
    pts = np.vstack([base, arc]) if cylinder_length > 0 else arc
    pts[-1, 0] = 0.0
    return pts


def form(p: Mapping[str, float]) -> Form:
    """The capsule as a form: a cylinder of ``radius`` to ``cylinder_length``, a hemisphere,
    no map; its symmetry repeats any sliver of azimuths (the check samples 4 of its grid's)."""
    radius = p["radius"]
    return Form(lambda z: np.full(np.shape(z), radius), p["cylinder_length"], radius, radius, lambda q: q,
                (0.0, 4 * 2 * math.pi / GRID[0]))


def check_params(params: Mapping[str, float], where: str = "membrane") -> dict[str, float]:
    """The capsule's parameters (DEFAULTS) filled and checked (``scenes.shapes.form.check_form``)."""
    return check_form(PARAMETERS, form, params, where)


def shape_mesh(params: Mapping[str, float], base_z: float, edge: float) -> trimesh.Trimesh:
    """The capsule of ``params`` (checked) in the tube frame, open at ``base_z``, triangles of
    edge about ``edge`` (metres): exactly :func:`mesh`'s for those numbers."""
    p, base_z, edge = mesh_arguments(PARAMETERS, form, params, base_z, edge)
    return revolve(profile(p["radius"], p["cylinder_length"], base_z), edge)


def membrane_params(params: Mapping[str, float], where: str) -> dict[str, float]:
    """None: a capsule's size is its table's own keys (TABLE_KEYS)."""
    return no_params(params, NAME, SIZE_FROM, where)


def check(membrane, where: str) -> None:
    """A capsule's thickness is radius - core_radius: it takes no ``thickness``."""
    if membrane.thickness is not None:
        raise ValueError(f"{where}.thickness: a capsule's thickness is radius - core_radius; drop the key")


def tube(membrane) -> Tube:
    """The capsule's body: the membrane's radius over the glass' core_radius, the cylinder's
    top at base_z + cylinder_length."""
    return Tube(membrane.radius, membrane.core_radius, membrane.base_z, membrane.base_z + membrane.cylinder_length)


def mesh(membrane) -> trimesh.Trimesh:
    """The membrane's outer surface in the tube frame, metres (cylinder + hemispherical tip),
    triangles of edge about ``membrane.mesh_edge``."""
    return revolve(profile(membrane.radius, membrane.cylinder_length, membrane.base_z), membrane.mesh_edge)


def regions(membrane, points: np.ndarray, inside: np.ndarray) -> dict[str, np.ndarray]:
    """The tip, beyond the cylinder's junction with the hemisphere, and the body below it."""
    return tip_and_body(points, inside, tube(membrane).junction_z)
