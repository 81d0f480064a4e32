"""Membrane geometry: a sensor spec's membrane mesh, its digest for cache keys, and the
faces where a mesh crosses itself.

Each shape family (``scenes.shapes``) builds its own mesh; :func:`membrane_mesh` asks the
spec's family for it and seats it in the camera frame.
"""

from __future__ import annotations

import numpy as np
import trimesh
from scipy import spatial

from .shapes import family
from .spec import SensorSpec

#: Slack of the crossing test, as a fraction of an edge and in barycentric terms: faces
#: that only touch count as crossing, rounding error on a shared corner does not.
CROSSING_TOL = 1e-9


def membrane_mesh(spec: SensorSpec) -> trimesh.Trimesh:
    """The membrane of a sensor spec in the camera frame, metres: its shape family's mesh
    (``scenes.shapes``), seated as the camera spec says (``CameraSpec.tube_to_camera``)
    where the family generates it in the tube's frame; a mesh file's is read, placed by
    its ``mesh_transform`` and checked (``scenes.shapes.mesh``)."""
    m = spec.membrane
    shape = family(m.shape)
    mesh = shape.mesh(m)
    if not shape.SEATED:
        return mesh
    pose = spec.camera.tube_to_camera()
    if not np.array_equal(pose, np.eye(4)):
        mesh.apply_transform(pose)
    return mesh


def mesh_digest(mesh: trimesh.Trimesh) -> str:
    """Stable hash of vertices and faces, for cache keys."""
    import hashlib

    h = hashlib.sha256()
    h.update(np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(mesh.faces, dtype=np.int64).tobytes())
    return h.hexdigest()[:16]


def crossing_faces(mesh: trimesh.Trimesh, faces: np.ndarray | None = None) -> np.ndarray:
    """Faces of a welded mesh that another face crosses (where the mesh intersects itself).

    Two faces that share no vertex intersect when an edge of one passes through the other;
    every pair of triangles meeting at an angle has such an edge. Faces lying in one plane
    are not tested.

    Parameters
    ----------
    faces : (K,) int, faces that moved: only pairs with one of them are tested (the
        edges of these faces against every face near them, and the edges of the faces
        near them against these), as two faces that did not move cannot have come to
        cross. None tests all pairs.

    Returns
    -------
    (C,) int, sorted indices of the faces that an edge crosses.
    """
    tri = np.asarray(mesh.triangles)
    if faces is None:
        _, ok = trimesh.triangles.normals(tri)
        planar = np.flatnonzero(ok)  # a zero-area face has no plane to be crossed
        return _crossed(mesh, planar, planar)
    faces = np.unique(np.asarray(faces, dtype=np.int64))
    if len(faces) == 0:
        return faces
    # Near: every face whose bounding sphere (about its centroid) meets a moved face's;
    # two triangles that cross share a point, so their spheres meet.
    centre, radius = _spheres(tri)
    tree = spatial.cKDTree(centre[faces])
    reach = radius[faces].max()
    large = radius > 2 * np.median(radius[faces])
    near = []
    for group in (np.flatnonzero(~large), np.flatnonzero(large)):
        if len(group):
            hits = tree.query_ball_point(centre[group], radius[group] + reach, return_length=True)
            near.append(group[hits > 0])
    near = np.concatenate(near)
    involved = np.union1d(near, faces)
    _, ok = trimesh.triangles.normals(tri[involved])
    planar = np.zeros(len(tri), bool)
    planar[involved[ok]] = True  # a zero-area face has no plane to be crossed
    near, moved = near[planar[near]], faces[planar[faces]]
    return np.union1d(_crossed(mesh, moved, near), _crossed(mesh, near, moved))


def _spheres(tri: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each triangle's (T, 3) centroid and (T,) the radius about it that holds the triangle."""
    centre = tri.mean(axis=1)
    return centre, np.linalg.norm(tri - centre[:, None], axis=2).max(axis=1)


def _near_pairs(mid: np.ndarray, half: np.ndarray, tri: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Broad phase: (edge, face) index pairs close enough to cross.

    An edge (midpoint ``mid``, half-length ``half``) can only meet a triangle whose
    centroid lies within half + the triangle's circumradius about its centroid. Faces
    much larger than the median, and edges much longer, are searched apart, with their own
    reach, so that a few large ones (the base ring) do not widen every search.
    """
    centre, radius = _spheres(tri)
    large = radius > 2 * np.median(radius)
    long = half > 2 * np.median(half)
    edges, faces = [np.zeros(0, np.int64)], [np.zeros(0, np.int64)]
    for lines in (np.flatnonzero(~long), np.flatnonzero(long)):
        if len(lines) == 0:
            continue
        edge_tree = spatial.cKDTree(mid[lines])
        for group in (np.flatnonzero(~large), np.flatnonzero(large)):
            if len(group) == 0:
                continue
            reach = float(half[lines].max() + radius[group].max())
            pairs = edge_tree.sparse_distance_matrix(spatial.cKDTree(centre[group]), reach, output_type="ndarray")
            i, j = lines[pairs["i"]], group[pairs["j"]]
            close = pairs["v"] <= half[i] + radius[j]  # each pair's own reach: its spheres meet
            edges.append(i[close])
            faces.append(j[close])
    return np.concatenate(edges), np.concatenate(faces)


def _crossed(mesh: trimesh.Trimesh, edge_faces: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """The faces among ``faces`` that an edge of ``edge_faces`` passes through."""
    if len(edge_faces) == 0 or len(faces) == 0:
        return np.zeros(0, np.int64)
    F = np.asarray(mesh.faces)
    tri = np.asarray(mesh.triangles)[faces]
    normals = trimesh.triangles.normals(tri)[0]
    edges = np.unique(np.sort(F[edge_faces][:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1), axis=0)
    a, b = mesh.vertices[edges[:, 0]], mesh.vertices[edges[:, 1]]
    edge, face = _near_pairs((a + b) / 2, np.linalg.norm(b - a, axis=1) / 2, tri)
    low, high = np.minimum(a, b), np.maximum(a, b)
    boxes = ((low[edge] <= tri.max(axis=1)[face]) & (high[edge] >= tri.min(axis=1)[face])).all(axis=1)
    edge, face = edge[boxes], face[boxes]
    apart = ~(F[faces][face][:, :, None] == edges[edge][:, None, :]).any(axis=(1, 2))
    edge, face = edge[apart], face[apart]
    length = np.linalg.norm(b - a, axis=1)
    hit, valid, t = trimesh.intersections.planes_lines(
        tri[face, 0], normals[face], a[edge], ((b - a) / length[:, None])[edge], return_distance=True
    )
    edge, face = edge[valid], face[valid]
    along = (t >= -CROSSING_TOL * length[edge]) & (t <= (1 + CROSSING_TOL) * length[edge])
    bary = trimesh.triangles.points_to_barycentric(tri[face], hit)
    inside = (bary >= -CROSSING_TOL).all(axis=1)
    return np.unique(faces[face[along & inside]])
