"""The deformed membrane rebuilt as a closed elastomer solid, from a contact depth map.

The outer surface is refined, then every vertex the camera sees is moved along its camera
ray to the elastically smoothed depth D_def (the same membrane model as the fast path).
The elastomer is the closed solid between that surface and the glass core (the undeformed
surface offset inwards by the membrane's thickness), closed at the base by a ring.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy import ndimage

from scenes.camera import Camera, check_depth, project
from scenes.elastic import deform
from scenes.spec import SensorSpec

#: Target edge of the refined outer surface, metres (a pixel spans ~0.15 mm at the tip).
REFINED_EDGE_M = 0.25e-3
#: Depth changes below this are not contact, metres.
CONTACT_EPS_M = 1e-6
#: The deformed surface must stay at least this far from the glass core, metres.
MIN_GAP_M = 0.1e-3
#: A face whose normal turns by more than this has folded over, radians.
MAX_FACE_TURN_RAD = np.radians(80.0)
#: Slack of the crossing test, as a fraction of an edge and in barycentric terms: faces
#: that only touch count as crossing, rounding error on a shared corner does not.
CROSSING_TOL = 1e-9


@dataclass(frozen=True)
class Elastomer:
    """The elastomer as three surfaces that together bound a closed solid.

    outer : the painted outer surface, deformed; normals point out of the elastomer.
    inner : the interface with the glass core; normals point out of the elastomer (into
        the glass).
    base : the ring that closes the bottom; normals point down, out of the elastomer.
    thickness : membrane thickness, metres.
    """

    outer: trimesh.Trimesh
    inner: trimesh.Trimesh
    base: trimesh.Trimesh
    thickness: float

    def solid(self) -> trimesh.Trimesh:
        """The three surfaces welded into one closed mesh."""
        mesh = trimesh.util.concatenate([self.outer, self.inner, self.base])
        mesh.merge_vertices(merge_tex=True, merge_norm=True)  # weld by position alone
        return mesh


def refine(mesh: trimesh.Trimesh, edge: float = REFINED_EDGE_M) -> trimesh.Trimesh:
    """Midpoint-subdivide every face until no edge exceeds ``edge`` (keeps it manifold)."""
    vertices, faces = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge=edge)
    return trimesh.Trimesh(vertices, faces, process=True)


def sample_depth(depth: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear samples of an (H, W) map at (K, 2) pixel coordinates (u, v)."""
    return ndimage.map_coordinates(depth, [uv[:, 1], uv[:, 0]], order=1, mode="nearest")


def displace(
    outer: trimesh.Trimesh, camera: Camera, d_def: np.ndarray, ref_depth: np.ndarray, thickness: float
) -> trimesh.Trimesh:
    """Move the vertices the camera sees along their rays to planar depth D_def.

    Raises ValueError when the surface would pass within MIN_GAP_M of the glass core or
    fold over (a face normal turning by more than MAX_FACE_TURN_RAD).
    """
    V = np.asarray(outer.vertices, dtype=np.float64)
    ahead = V[:, 2] > 1e-6
    uv = np.full((len(V), 2), -1.0)
    uv[ahead] = project(V[ahead], camera)
    seen = ahead & (uv[:, 0] >= 0) & (uv[:, 0] <= camera.width - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= camera.height - 1)
    z_def = sample_depth(d_def, uv[seen])
    z_ref = sample_depth(ref_depth, uv[seen])
    pressed = z_def < z_ref - CONTACT_EPS_M
    moved = np.flatnonzero(seen)[pressed]
    new = V.copy()
    new[moved] = V[moved] * (z_def[pressed] / V[moved, 2])[:, None]
    normals = np.asarray(outer.vertex_normals)
    push = np.einsum("ij,ij->i", V[moved] - new[moved], normals[moved])  # inwards, metres
    if len(push) and push.max() > thickness - MIN_GAP_M:
        bad = int((push > thickness - MIN_GAP_M).sum())
        raise ValueError(
            f"depth map pushes the membrane through the glass core at {bad} vertices "
            f"(up to {push.max() * 1e3:.2f} mm into a {thickness * 1e3:.2f} mm membrane, "
            f"keeping a {MIN_GAP_M * 1e3:.1f} mm gap)"
        )
    deformed = trimesh.Trimesh(new, outer.faces, process=False)
    turn = np.einsum("ij,ij->i", deformed.face_normals, outer.face_normals)
    folded = turn < np.cos(MAX_FACE_TURN_RAD)
    if folded.any():
        raise ValueError(
            f"the deformed membrane folds over itself at {int(folded.sum())} faces (a face normal turns by more "
            f"than {np.degrees(MAX_FACE_TURN_RAD):.0f} deg); the depth map is too steep for a membrane"
        )
    return deformed


def elastomer(
    membrane: trimesh.Trimesh,
    spec: SensorSpec,
    camera: Camera,
    depth: np.ndarray | None = None,
    ref_depth: np.ndarray | None = None,
    edge: float = REFINED_EDGE_M,
    smooth: bool = True,
) -> Elastomer:
    """Build the elastomer solid of a (possibly deformed) membrane.

    Parameters
    ----------
    membrane : the undeformed outer membrane surface, open at its base, camera frame.
    depth : (H, W) float, metres, contact depth map D (None: no contact).
    ref_depth : (H, W) float, metres, D_ref; required with ``depth``.
    smooth : apply the elastic smoothing D_def = min(D, D_ref - G * (D_ref - D)) first.
    """
    thickness = spec.membrane.radius - spec.membrane.core_radius
    outer0 = refine(membrane, edge)
    outer = outer0
    if depth is not None:
        if ref_depth is None:
            raise ValueError("ref_depth is required with a depth map")
        depth = check_depth(depth, camera).astype(np.float64)
        ref_depth = check_depth(ref_depth, camera, "ref_depth").astype(np.float64)
        d_def = deform(depth, ref_depth, spec.elastic) if smooth else depth
        outer = displace(outer0, camera, d_def, ref_depth, thickness)
    normals = np.asarray(outer0.vertex_normals)
    inner = trimesh.Trimesh(np.asarray(outer0.vertices) - thickness * normals, outer0.faces, process=False)
    inner.invert()  # normals into the glass: out of the elastomer
    base = _base_ring(outer0, inner)
    result = Elastomer(outer, inner, base, thickness)
    moved = np.any(np.asarray(outer.vertices) != np.asarray(outer0.vertices), axis=1)
    check_solid(result, changed=np.flatnonzero(moved[outer.faces].any(axis=1)))
    return result


def _base_ring(outer: trimesh.Trimesh, inner: trimesh.Trimesh) -> trimesh.Trimesh:
    """Quads joining the open boundary loop of the outer surface to the inner one's."""
    loops = outer.outline().entities
    if len(loops) != 1:
        raise ValueError(f"the membrane must have exactly one open boundary (its base), got {len(loops)}")
    loop = np.asarray(loops[0].points)
    if loop[0] == loop[-1]:
        loop = loop[:-1]
    n = len(loop)
    V = np.vstack([outer.vertices[loop], inner.vertices[loop]])
    a, b = np.arange(n), (np.arange(n) + 1) % n
    faces = np.vstack([np.c_[a, b, n + b], np.c_[a, n + b, n + a]])
    ring = trimesh.Trimesh(V, faces, process=False)
    # Orient the ring to face away from the solid, towards the membrane's open side.
    outward = outer.vertices[loop].mean(axis=0) - outer.vertices.mean(axis=0)
    if np.dot(ring.face_normals.mean(axis=0), outward) < 0:
        ring.invert()
    return ring


def check_solid(solid: Elastomer, changed: np.ndarray | None = None) -> None:
    """The three surfaces must weld into a watertight, consistently wound solid that does
    not intersect itself.

    changed : (K,) int, indices of the outer faces that moved (the solid lists the outer
        faces first); only the faces near them are tested for crossings. None tests every
        face, which takes seconds on a finely refined membrane.
    """
    mesh = solid.solid()
    if not mesh.is_watertight:
        raise ValueError("the elastomer is not watertight (the membrane's base loop did not close)")
    if not mesh.is_winding_consistent:
        raise ValueError("the elastomer's surfaces are not consistently wound")
    if mesh.volume <= 0:
        raise ValueError("the elastomer's normals point inwards (negative volume)")
    crossed = crossing_faces(mesh, changed)
    if len(crossed):
        raise ValueError(
            f"the elastomer intersects itself at {len(crossed)} faces: the deformed membrane passes through "
            "itself or through the glass core"
        )


def crossing_faces(mesh: trimesh.Trimesh, faces: np.ndarray | None = None) -> np.ndarray:
    """Faces of a welded mesh that another face crosses (where the mesh intersects itself).

    Two faces that share no vertex intersect when an edge of one passes through the other;
    every pair of triangles meeting at an angle has such an edge. Faces lying in one plane
    are not tested.

    Parameters
    ----------
    faces : (K,) int, the faces to test against every face near them (in their common
        bounding box); None tests all faces.

    Returns
    -------
    (C,) int, sorted indices of the faces that an edge crosses.
    """
    F = np.asarray(mesh.faces)
    tri = np.asarray(mesh.triangles)
    lo, hi = tri.min(axis=1), tri.max(axis=1)
    near = np.arange(len(F))
    if faces is not None:
        faces = np.asarray(faces, dtype=np.int64)
        if len(faces) == 0:
            return faces
        box_lo, box_hi = lo[faces].min(axis=0), hi[faces].max(axis=0)
        near = np.flatnonzero((lo <= box_hi).all(axis=1) & (hi >= box_lo).all(axis=1))
    normals, ok = trimesh.triangles.normals(tri[near])
    near = near[ok]  # a zero-area face has no plane to be crossed
    edges = np.unique(np.sort(F[near][:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1), axis=0)
    a, b = mesh.vertices[edges[:, 0]], mesh.vertices[edges[:, 1]]
    # Broad phase: faces whose bounding box meets the edge's (trimesh's ray queries would
    # take the box of the whole ray instead).
    tree = trimesh.util.bounds_tree(np.column_stack([lo[near], hi[near]]))
    candidates, counts = tree.intersection_v(np.minimum(a, b), np.maximum(a, b))
    edge = np.repeat(np.arange(len(edges)), counts.astype(np.int64))
    face = candidates.astype(np.int64)
    apart = ~(F[near][face][:, :, None] == edges[edge][:, None, :]).any(axis=(1, 2))
    edge, face = edge[apart], face[apart]
    length = np.linalg.norm(b - a, axis=1)
    hit, valid, t = trimesh.intersections.planes_lines(
        tri[near][face, 0], normals[face], a[edge], ((b - a) / length[:, None])[edge], return_distance=True
    )
    edge, face = edge[valid], face[valid]
    along = (t >= -CROSSING_TOL * length[edge]) & (t <= (1 + CROSSING_TOL) * length[edge])
    bary = trimesh.triangles.points_to_barycentric(tri[near][face], hit)
    inside = (bary >= -CROSSING_TOL).all(axis=1)
    return np.unique(near[face[along & inside]])
