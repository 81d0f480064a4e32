"""How a membrane surface curves at given points, and the kind of region that makes it.

A light field that follows the membrane (plane, geodesic, transport) and one that does
not (linear) disagree most where the surface bends both ways: a saddle between a paw's
toes, a waist, a concave trough. Studies group their contacts and pixels by these
classes (``studies.pbr_field_comparison``).

The principal curvatures come from libigl's ``principal_curvature``: at each vertex, a
quadric fitted by least squares to the vertices within a ball of radius ``radius``
(Panozzo, Puppo and Rocca, "Efficient multi-scale curvature and crease estimation",
2010). On a sphere or a torus of 256 x 128 sections it is within 1 % of the closed form.
(trimesh's discrete curvature measures, tried first, integrate the mean and Gaussian
curvature over the ball: the mean is right, but the Gaussian measure's few-percent error
splits an umbilic point's curvatures by +-15 %.) Values at points between vertices are
interpolated linearly on the face nearest them (``scenes.proximity.interpolate``). The ball
smooths detail finer than its radius, which is what a contact a few millimetres across
feels.

Sign: convex positive, for a mesh whose normals point outward (a sphere of radius R has
curvatures 1/R, 1/R).
"""

from __future__ import annotations

import math

import numpy as np
import trimesh

from .proximity import interpolate

#: The ball over which curvature is averaged, metres: about a tap's contact radius.
CURVATURE_RADIUS_M = 2.0e-3
#: A direction curved less than 1 / this, metres, counts as flat (a 50 mm radius).
FLAT_RADIUS_M = 0.05
#: The kinds of region, by the signs of the two principal curvatures (k1 <= k2):
#: convex (+, +), cylindrical (0, +), flat (0, 0), saddle (-, +), trough (-, 0),
#: concave (-, -); 0 meaning within 1 / FLAT_RADIUS_M of zero.
CLASSES = ("convex", "cylindrical", "flat", "saddle", "trough", "concave")


def vertex_curvatures(mesh: trimesh.Trimesh, radius: float = CURVATURE_RADIUS_M) -> np.ndarray:
    """Principal curvatures at each vertex (V, 2), 1/m, k[:, 0] <= k[:, 1], convex positive.

    mesh : a triangle mesh, metres, normals outward; open or closed.
    radius : metres, the ball the quadric is fitted over; it must span at least two of
        the mesh's mean edges (libigl measures it in whole mean edges, rounded).
    """
    import igl

    if not (math.isfinite(radius) and radius > 0):
        raise ValueError(f"radius must be a positive number of metres, got {radius}")
    edge = float(np.mean(mesh.edges_unique_length))
    if not radius >= 2 * edge:
        raise ValueError(f"radius ({radius * 1e3:g} mm) must span at least two of the mesh's mean edges "
                         f"({edge * 1e3:.3g} mm each): refine the mesh or widen the ball")
    _, _, k_max, k_min, _ = igl.principal_curvature(np.ascontiguousarray(mesh.vertices, dtype=np.float64),
                                                     np.ascontiguousarray(mesh.faces, dtype=np.int64),
                                                     int(round(radius / edge)), False)
    return np.sort(np.stack([k_min, k_max], axis=1), axis=1)


def principal_curvatures(mesh: trimesh.Trimesh, points: np.ndarray,
                         radius: float = CURVATURE_RADIUS_M) -> np.ndarray:
    """Principal curvatures (N, 2) at points on or near the mesh, 1/m, k[:, 0] <= k[:, 1],
    convex positive: ``vertex_curvatures`` interpolated on the nearest face.

    points : (N, 3) float, metres, within about an edge of the surface.
    """
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or not np.isfinite(points).all():
        raise ValueError(f"points must be a finite (N, 3) array, got shape {points.shape}")
    k = vertex_curvatures(mesh, radius)
    if len(points) == 0:
        return np.zeros((0, 2))
    return np.sort(np.stack([interpolate(mesh, k[:, i], points) for i in range(2)], axis=1), axis=1)


def classify(k: np.ndarray, flat_radius: float = FLAT_RADIUS_M) -> np.ndarray:
    """The class of each point (N,) str, one of CLASSES, from its curvatures k (N, 2)."""
    k = np.asarray(k, dtype=np.float64)
    if k.ndim != 2 or k.shape[1] != 2 or not np.isfinite(k).all():
        raise ValueError(f"k must be a finite (N, 2) array of principal curvatures, got shape {k.shape}")
    if not (math.isfinite(flat_radius) and flat_radius > 0):
        raise ValueError(f"flat_radius must be a positive number of metres, got {flat_radius}")
    tol = 1.0 / flat_radius
    lo, hi = np.sort(k, axis=1).T
    sign = lambda x: np.where(x > tol, 1, np.where(x < -tol, -1, 0))  # noqa: E731
    table = {(1, 1): "convex", (0, 1): "cylindrical", (0, 0): "flat", (-1, 1): "saddle", (-1, 0): "trough",
             (-1, -1): "concave"}
    slo, shi = sign(lo), sign(hi)
    out = np.empty(len(k), dtype=object)
    for (a, b), name in table.items():
        out[(slo == a) & (shi == b)] = name
    return out.astype(str)
