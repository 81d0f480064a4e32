"""The thumb family: a flattened, leaning fingertip over a core derived by offsetting it.

A form of ``scenes.shapes.form``. The canonical surface is a cylinder of radius ``R0`` up
to ``Z_c = length - tip_height``, closed by a half spheroid of semi-axes ``(R0, R0,
tip_height)``; ``R0`` is the mean radius of the cross-section below, so that the map
keeps edge lengths near ``edge`` on average. The map is::

    x = a X / R0                                   a = width / 2
    y = b psi(Y / R0) - tip_lean * t**3           b = depth / 2
    z = base_z + Z                                 t = max(0, (Z - Z_c) / tip_height)
    psi(v) = v                        (v >= 0, the back: a half ellipse)
    psi(v) = v + f v**3 (1 + v)       (v < 0, the pad, on -y; f = pad_flatness)

The cross-section is an ellipse, wider (x) than deep (y), whose -y half (the pad) is
flattened: its curvature at the pad's centre is ``1 - pad_flatness`` times the back's.
``psi`` is C2 (its third derivative jumps at v = 0) and increasing, as ``t**3`` is C2 at
the tip's start. The tip is a half spheroid lower than the cross-section is wide
(``tip_height <= width / 2``), sheared towards the pad: the apex sits at ``(0,
-tip_lean, base_z + length)``, and the +z axis leaves the membrane just behind it. (In
the camera frame, x right and y down, the pad faces the image's top.)

A spec gives its parameters in ``[membrane.params]`` and its elastomer's ``thickness``;
``scenes.body`` derives the core.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np
import trimesh

from .interface import derived_core, tip_and_body
from .form import Form, check_form, mesh_arguments, warped_mesh
from .params import Parameters

NAME = "thumb"
TABLE_KEYS: tuple[str, ...] = ()
SIZE_FROM = "[membrane.params]"
CORE_FROM = "thickness"
SEATED = True
FILLS_VIEW = False
PUBLISHED = False
REGIONS = ("tip", "body")

DEFAULTS: dict[str, float] = {
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
}

BOUNDS: dict[str, tuple[float, float]] = {
    "width": (0.021, 0.030),  # m: wider than deep by 15 % at least
    "depth": (0.016, 0.018),  # m: the core clearance
    "length": (0.035, 0.065),  # m
    "tip_height": (0.009, 0.0105),  # m: the core clearance; flatter than wide
    "pad_flatness": (0.0, 0.8),  # -: the pad shoulders' convex radius
    "tip_lean": (0.0, 0.002),  # m: the core clearance behind the tip
}

#: Each parameter's unit: "m", "rad" or "-" (dimensionless).
UNITS: dict[str, str] = {"width": "m", "depth": "m", "length": "m", "tip_height": "m", "pad_flatness": "-",
                         "tip_lean": "m"}

PARAMETERS = Parameters(NAME, DEFAULTS, BOUNDS, UNITS)


def _psi(v: np.ndarray, flatness: float) -> np.ndarray:
    """psi(v): the back (v >= 0) as it is, the pad (v < 0) flattened, monotone on [-1, 1]."""
    return np.where(v < 0, v + flatness * v**3 * (1.0 + v), v)


def form(p: Mapping[str, float]) -> Form:
    """The thumb of filled parameters ``p`` as a form (module doc)."""
    a, b = p["width"] / 2, p["depth"] / 2
    f, h, lean = p["pad_flatness"], p["tip_height"], p["tip_lean"]
    z_c = p["length"] - h
    t = np.linspace(0.0, 2 * math.pi, 2049)
    section = np.stack([a * np.cos(t), b * _psi(np.sin(t), f)], axis=1)
    r0 = float(np.linalg.norm(np.diff(section, axis=0), axis=1).sum()) / (2 * math.pi)

    def warp(q: np.ndarray) -> np.ndarray:
        tip = np.clip((q[:, 2] - z_c) / h, 0.0, None)
        return np.stack([a * q[:, 0] / r0, b * _psi(q[:, 1] / r0, f) - lean * tip**3, q[:, 2]], axis=1)

    # Mirror-symmetric about x = 0: the half x >= 0 is the whole.
    return Form(lambda z: np.full(np.shape(z), r0), z_c, r0, h, warp, (-math.pi / 2, math.pi / 2))


def check_params(params: Mapping[str, float], where: str = "membrane") -> dict[str, float]:
    """The thumb's parameters (DEFAULTS) filled and checked (``scenes.shapes.form.check_form``)."""
    return check_form(PARAMETERS, form, params, where)


def shape_mesh(params: Mapping[str, float], base_z: float, edge: float) -> trimesh.Trimesh:
    """The thumb of ``params`` (checked) in the tube frame, open at ``base_z``, triangles of
    edge about ``edge`` (metres, at most ``scenes.shapes.form.MAX_EDGE_M``)."""
    p, base_z, edge = mesh_arguments(PARAMETERS, form, params, base_z, edge)
    return warped_mesh(form(p), base_z, edge)


# The family's interface (``scenes.shapes.interface``): its core is derived.
membrane_params, check, tube, mesh = derived_core(check_params, shape_mesh)


def regions(membrane, points: np.ndarray, inside: np.ndarray) -> dict[str, np.ndarray]:
    """The tip (the top share of the visible membrane along the axis) and the body."""
    return tip_and_body(points, inside)
