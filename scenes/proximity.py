"""Query mesh-point proximity: the nearest face and point of a mesh, the exact distance to
its surface, and per-vertex values interpolated at points near it.

The membrane's body (``scenes.body``: the thickness under a point), its curvature
(``scenes.curvature``), the protocols and the renderers' LED placement all sample a mesh
at points this way.
"""

from __future__ import annotations

import numpy as np
import trimesh
from scipy import spatial

#: Nearest faces searched for a point's closest point on a mesh (``closest_faces``).
NEAREST_FACES = 8


def interpolate(mesh: trimesh.Trimesh, values: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N,) per-vertex ``values`` (V,) of a mesh, linearly interpolated at the nearest
    points of its surface to ``points`` (N, 3)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    values = np.asarray(values, dtype=np.float64)
    if values.shape != (len(mesh.vertices),):
        raise ValueError(f"values must be ({len(mesh.vertices)},), one per vertex, got shape {values.shape}")
    if np.ptp(values) == 0:
        return np.full(len(points), float(values[0]))
    face, closest = closest_faces(mesh, points)
    tri = np.asarray(mesh.triangles)[face]
    bary = np.clip(trimesh.triangles.points_to_barycentric(tri, closest), 0.0, 1.0)
    bary /= bary.sum(axis=1, keepdims=True)
    return (values[np.asarray(mesh.faces)[face]] * bary).sum(axis=1)


def closest_faces(mesh: trimesh.Trimesh, points: np.ndarray, k: int = NEAREST_FACES) -> tuple[np.ndarray, np.ndarray]:
    """The face (N,) and closest point (N, 3) of a mesh to points (N, 3) near it, among the
    ``k`` faces whose centroids are nearest (exact for points within about an edge)."""
    tri = np.asarray(mesh.triangles)
    k = min(k, len(tri))
    _, near = spatial.cKDTree(tri.mean(axis=1)).query(points, k=k)
    near = near.reshape(len(points), k)
    cand = trimesh.triangles.closest_point(tri[near.ravel()], np.repeat(points, k, axis=0)).reshape(-1, k, 3)
    best = np.argmin(np.linalg.norm(cand - points[:, None], axis=2), axis=1)
    rows = np.arange(len(points))
    return near[rows, best], cand[rows, best]


def surface_distance(mesh: trimesh.Trimesh, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The exact distance (N,) from points (N, 3) to a mesh's surface, metres, the
    closest points (N, 3) and their faces (N,).

    The closest point lies within the nearest vertex's distance, so only faces whose
    centroids lie within that plus the largest face's circumradius are tested: a sparse,
    vectorised form of trimesh.proximity, worked in millimetres as trimesh's tolerances
    are absolute (at metre scale they misplace closest points).
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3) * 1e3
    tri = np.asarray(mesh.triangles) * 1e3
    centre = tri.mean(axis=1)
    reach = float(np.linalg.norm(tri - centre[:, None], axis=2).max())
    nearest, _ = spatial.cKDTree(np.asarray(mesh.vertices) * 1e3).query(points)
    lists = spatial.cKDTree(centre).query_ball_point(points, nearest * (1 + 1e-9) + reach)
    count = np.fromiter((len(c) for c in lists), np.int64, len(points))
    face = np.fromiter((f for c in lists for f in c), np.int64, int(count.sum()))
    which = np.repeat(np.arange(len(points)), count)
    closest = trimesh.triangles.closest_point(tri[face], points[which])
    d = np.linalg.norm(closest - points[which], axis=1)
    order = np.lexsort((d, which))
    first = order[np.searchsorted(which[order], np.arange(len(points)))]
    return d[first] * 1e-3, closest[first] * 1e-3, face[first]
