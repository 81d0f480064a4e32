"""The paw family: a waisted capsule whose tip carries toes, over a core derived by offsetting it.

A form of ``scenes.shapes.form``. The canonical surface revolves ``r(Z) = radius -
waist_depth * B((Z - Z_w) / h_w)`` (``Z_w = WAIST_CENTRE * cylinder_length``, ``h_w =
WAIST_HALF_LENGTH * cylinder_length``) up to ``Z_c = cylinder_length``, closed by a
hemisphere of ``radius`` about ``c = (0, 0, Z_c)``. The map leaves the body as it is and
moves each tip point ``c + radius u`` (``u`` unit) along ``u``::

    p = c + (radius + H(u)) u,   H(u) = toe_height * sum_k B(|u - d_k| / (2 sin(w / 2)))
    B(s) = (1 - s**2)**3 for |s| < 1, else 0            (C2, a smooth bump)
    d_k = (sin s_t cos(2 pi k / n), sin s_t sin(2 pi k / n), cos s_t)

with ``n = toes``, ``s_t = toe_spread`` the toes' angle from the axis and ``w`` each
toe's angular half-width: ``TOE_WIDTH_PER_GAP`` times the angle between neighbouring toes
(so neighbours overlap into saddles), at most ``TOE_REACH_RAD - toe_spread`` (so no toe
reaches the tip's start, where the map is the identity).

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

NAME = "paw"
TABLE_KEYS: tuple[str, ...] = ()
SIZE_FROM = "[membrane.params]"
CORE_FROM = "thickness"
SEATED = True
FILLS_VIEW = False
PUBLISHED = False
REGIONS = ("tip", "body")

#: The paw's waist: its centre and half-length as shares of cylinder_length.
WAIST_CENTRE = 0.55
WAIST_HALF_LENGTH = 0.35
#: The paw's toe half-width as a share of the angle between neighbouring toes (> 1/2:
#: neighbours overlap, leaving a saddle between them).
TOE_WIDTH_PER_GAP = 0.8
#: Largest angle from the axis a toe reaches, rad (below pi/2: the toes stay on the tip).
TOE_REACH_RAD = 1.4

DEFAULTS: dict[str, float] = {
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
}

BOUNDS: dict[str, tuple[float, float]] = {
    "radius": (0.0095, 0.013),  # m: the core clearance at the waist
    "cylinder_length": (0.030, 0.050),  # m: star-shaped past the waist
    "toes": (3.0, 5.0),  # -: more toes are narrower: 6 curve too tightly at the highest toe_height
    "toe_height": (0.0, 0.0012),  # m: the toes' convex and the valleys' concave radii
    "toe_spread": (0.6, 0.8),  # rad: the toes' convex radius (their width shrinks nearer the axis)
    "waist_depth": (0.0, 0.0015),  # m: the core clearance; star-shaped
}

#: Each parameter's unit: "m", "rad" or "-" (dimensionless).
UNITS: dict[str, str] = {"radius": "m", "cylinder_length": "m", "toes": "-", "toe_height": "m", "toe_spread": "rad",
                         "waist_depth": "m"}

PARAMETERS = Parameters(NAME, DEFAULTS, BOUNDS, UNITS, whole=("toes",))


def _bump(s2: np.ndarray) -> np.ndarray:
    """B as a function of s**2: (1 - s**2)**3 inside the unit disc, 0 outside (C2)."""
    return np.where(s2 < 1.0, (1.0 - np.minimum(s2, 1.0)) ** 3, 0.0)


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


def form(p: Mapping[str, float]) -> Form:
    """The paw of filled parameters ``p`` as a form (module doc)."""
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
    return Form(r_body, z_c, radius, radius, warp, (0.0, math.pi / len(d)))


def check_params(params: Mapping[str, float], where: str = "membrane") -> dict[str, float]:
    """The paw's parameters (DEFAULTS) filled and checked (``scenes.shapes.form.check_form``)."""
    return check_form(PARAMETERS, form, params, where)


def shape_mesh(params: Mapping[str, float], base_z: float, edge: float) -> trimesh.Trimesh:
    """The paw of ``params`` (checked) in the tube frame, open at ``base_z``, triangles of
    edge about ``edge`` (metres, at most ``scenes.shapes.form.MAX_EDGE_M``)."""
    p, base_z, edge = mesh_arguments(PARAMETERS, form, params, base_z, edge)
    return warped_mesh(form(p), base_z, edge)


# The family's interface (``scenes.shapes.interface``): its core is derived.
membrane_params, check, tube, mesh = derived_core(check_params, shape_mesh)


def regions(membrane, points: np.ndarray, inside: np.ndarray) -> dict[str, np.ndarray]:
    """The tip (the top share of the visible membrane along the axis) and the body."""
    return tip_and_body(points, inside)
