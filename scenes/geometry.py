"""Membrane geometry: meshes built from the sensor spec or loaded from any file."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import trimesh
from scipy import spatial

from .spec import MAX_SENSOR_SIZE_M, MembraneSpec, SensorSpec

#: A mesh whose largest extent exceeds this (in the file's units) is not in metres.
MM_SUSPICION_EXTENT = MAX_SENSOR_SIZE_M
#: Slack of the crossing test, as a fraction of an edge and in barycentric terms: faces
#: that only touch count as crossing, rounding error on a shared corner does not.
CROSSING_TOL = 1e-9


def capsule_profile(radius: float, cylinder_length: float, base_z: float) -> np.ndarray:
    """Profile of a cylinder closed by a hemisphere, as a dense (r, z) polyline.

    Returns
    -------
    (K, 2) float64, metres: r >= 0 and z, from the open base to the pole (r = 0).
    """
    n_arc = 256
    z_top = base_z + cylinder_length
    theta = np.linspace(0.0, math.pi / 2, n_arc + 1)
    arc = np.stack([radius * np.cos(theta), z_top + radius * np.sin(theta)], axis=1)
    base = np.array([[radius, base_z]])
    pts = np.vstack([base, arc]) if cylinder_length > 0 else arc
    pts[-1, 0] = 0.0
    return pts


def _resample_profile(profile: np.ndarray, edge: float) -> np.ndarray:
    """Rings along the profile, spaced by the height of an equilateral triangle."""
    seg = np.linalg.norm(np.diff(profile, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    n = max(2, int(math.ceil(s[-1] / (edge * math.sqrt(3) / 2))))
    s_new = np.linspace(0.0, s[-1], n + 1)
    return np.stack([np.interp(s_new, s, profile[:, 0]), np.interp(s_new, s, profile[:, 1])], axis=1)


def _zip_rings(a0: int, na: int, ta: float, b0: int, nb: int, tb: float) -> list[tuple[int, int, int]]:
    """Triangulate the strip between two rings of na and nb vertices.

    Ring vertices k sit at angles t + 2 pi k / n; the strip is walked in angle order, so
    rings of different counts join with near-equilateral triangles.
    """
    # Start ring b at the vertex nearest ring a's first angle, unwrapped around it.
    shift = int(round((ta - tb) * nb / (2 * math.pi))) % nb if nb > 1 else 0
    tb0 = tb + 2 * math.pi * shift / nb
    tb0 += 2 * math.pi * round((ta - tb0) / (2 * math.pi))
    i = j = 0
    tris = []
    while i < na or j < nb:
        next_a = ta + 2 * math.pi * (i + 1) / na
        next_b = tb0 + 2 * math.pi * (j + 1) / nb
        ai, ai1 = a0 + i % na, a0 + (i + 1) % na
        bj, bj1 = b0 + (shift + j) % nb, b0 + (shift + j + 1) % nb
        if j >= nb or (i < na and next_a <= next_b):
            tris.append((ai, ai1, bj))
            i += 1
        else:
            if bj1 != bj:  # a pole (nb = 1) takes no b-steps
                tris.append((ai, bj1, bj))
            j += 1
    return tris


def revolve(profile: np.ndarray, edge: float) -> trimesh.Trimesh:
    """Surface of revolution about the z axis with near-equilateral triangles.

    Parameters
    ----------
    profile : (K, 2) float, metres
        (r, z) polyline from the open end to the far end; r = 0 at the end closes it
        with a pole vertex.
    edge : float, metres
        Target triangle edge length.

    Returns
    -------
    trimesh.Trimesh with outward-facing normals, open at the first profile ring.
    """
    profile = np.asarray(profile, dtype=np.float64)
    if profile.ndim != 2 or profile.shape[1] != 2 or len(profile) < 2:
        raise ValueError(f"profile must be (K >= 2, 2) (r, z), got shape {profile.shape}")
    if not np.all(np.isfinite(profile)) or np.any(profile[:, 0] < 0):
        raise ValueError("profile must be finite with r >= 0")
    if not edge > 0:
        raise ValueError(f"edge must be > 0 m, got {edge}")
    rings = _resample_profile(profile, edge)
    vertices, starts, counts, phases = [], [], [], []
    for k, (r, z) in enumerate(rings):
        n = 1 if r < edge * 1e-3 else max(3, int(round(2 * math.pi * r / edge)))
        phase = (k % 2) * math.pi / n
        t = phase + 2 * math.pi * np.arange(n) / n
        starts.append(sum(counts))
        counts.append(n)
        phases.append(phase)
        vertices.append(np.stack([r * np.cos(t), r * np.sin(t), np.full(n, z)], axis=1))
    faces = []
    for k in range(len(rings) - 1):
        faces += _zip_rings(starts[k], counts[k], phases[k], starts[k + 1], counts[k + 1], phases[k + 1])
    mesh = trimesh.Trimesh(np.vstack(vertices), np.array(faces, dtype=np.int64), process=False)
    # The walk above winds counter-clockwise seen from outside when z grows along the
    # profile; flip if the profile runs the other way.
    if rings[-1, 1] < rings[0, 1]:
        mesh.invert()
    return mesh


def capsule_mesh(membrane: MembraneSpec) -> trimesh.Trimesh:
    """GelTip-like membrane (cylinder + hemispherical tip) in the camera frame, metres."""
    profile = capsule_profile(membrane.radius, membrane.cylinder_length, membrane.base_z)
    return revolve(profile, membrane.mesh_edge)


def validate_mesh(mesh: trimesh.Trimesh, name: str = "mesh") -> trimesh.Trimesh:
    """Check a membrane mesh: faces present, finite vertices, valid indices, metres."""
    vertices = np.asarray(mesh.vertices)
    faces = np.asarray(mesh.faces)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) < 3:
        raise ValueError(f"{name}: vertices must be (N >= 3, 3), got shape {vertices.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) == 0:
        raise ValueError(f"{name}: needs triangle faces (M >= 1, 3), got shape {faces.shape}")
    if not np.all(np.isfinite(vertices)):
        bad = int(np.count_nonzero(~np.isfinite(vertices).all(axis=1)))
        raise ValueError(f"{name}: {bad} vertices are NaN or infinite")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise ValueError(f"{name}: face indices must be in [0, {len(vertices)}), got [{faces.min()}, {faces.max()}]")
    extent = float(np.max(vertices.max(axis=0) - vertices.min(axis=0)))
    if extent > MM_SUSPICION_EXTENT:
        raise ValueError(
            f"{name}: extent {extent:g} looks like millimetres, but metres were expected "
            f"(a sensor larger than {MM_SUSPICION_EXTENT:g} m is implausible); "
            "load it with units='mm' to scale by 0.001"
        )
    if extent <= 0:
        raise ValueError(f"{name}: all vertices coincide")
    areas = mesh.area_faces
    if np.count_nonzero(areas > 0) == 0:
        raise ValueError(f"{name}: all faces are degenerate (zero area)")
    return mesh


#: Metres per unit of a mesh file.
UNIT_SCALE = {"m": 1.0, "mm": 1e-3}


def read_mesh_file(path: str | Path, what: str = "mesh") -> trimesh.Trimesh:
    """Read a triangle mesh file as it is (file units, unprocessed).

    Raises FileNotFoundError, or ValueError naming the file when it is not a readable
    triangle mesh. ``what`` names the file's role in messages ("mesh", "indenter").
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what} file {path} does not exist")
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for malformed files
        raise ValueError(f"{what} file {path} could not be read as a triangle mesh: {exc}") from exc
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError(f"{what} file {path} holds no triangle faces (not a mesh, or unreadable)")
    return mesh


def load_mesh(path: str | Path, units: str = "m") -> trimesh.Trimesh:
    """Load any membrane mesh (STL, OBJ, PLY, ...) and return it in metres.

    Parameters
    ----------
    path : file readable by trimesh.
    units : "m" or "mm", the units of the file. A file that looks like millimetres while
        metres were declared is refused, never silently rescaled.
    """
    scale = UNIT_SCALE.get(units)
    if scale is None:
        raise ValueError(f"units must be 'm' or 'mm', got {units!r}")
    mesh = read_mesh_file(path, "mesh")
    # Validate before processing: trimesh's processing silently drops NaN vertices.
    validate_mesh(trimesh.Trimesh(np.asarray(mesh.vertices) * scale, mesh.faces, process=False), name=str(path))
    mesh = trimesh.Trimesh(np.asarray(mesh.vertices) * scale, mesh.faces, process=True)
    return validate_mesh(mesh, name=str(path))


def membrane_mesh(spec: SensorSpec) -> trimesh.Trimesh:
    """The membrane of a sensor spec in the camera frame, metres: generated (a capsule or
    a ``scenes.shapes`` family, seated as the camera spec says,
    ``CameraSpec.tube_to_camera``), or read from ``mesh_path`` and placed by
    ``mesh_transform``; checked by :func:`check_membrane`."""
    m = spec.membrane
    if m.shape == "mesh":
        mesh = load_mesh(m.mesh_path, units=m.mesh_units)
        if m.mesh_transform is not None:
            mesh.apply_transform(np.reshape(m.mesh_transform, (4, 4)))
        return check_membrane(mesh, f"membrane {m.mesh_path}")
    if m.shape == "capsule":
        mesh = capsule_mesh(m)
    elif m.shape == "pad":
        from .pad import pad_mesh

        mesh = pad_mesh(dict(m.params), m.base_z, m.mesh_edge)
    else:
        from .shapes import shape_mesh

        mesh = shape_mesh(m.shape, dict(m.params), m.base_z, m.mesh_edge)
    pose = spec.camera.tube_to_camera()
    if not np.array_equal(pose, np.eye(4)):
        mesh.apply_transform(pose)
    return mesh


def base_loop(mesh: trimesh.Trimesh, name: str = "membrane") -> np.ndarray:
    """(K,) int, the vertices of a membrane's one open boundary (its base), in order;
    ValueError naming ``name`` when it has none or several (holes)."""
    loops = [np.asarray(e.points) for e in mesh.outline().entities] if len(mesh.faces) else []
    if len(loops) != 1:
        raise ValueError(f"{name}: a membrane must be open at its base alone, with one boundary loop, got "
                         f"{len(loops)}" + (" (it has holes: the other loops)" if len(loops) > 1 else
                                           " (a closed surface has no base to seat on the glass)"))
    loop = loops[0]
    return loop[:-1] if loop[0] == loop[-1] else loop


def check_membrane(mesh: trimesh.Trimesh, name: str = "membrane") -> trimesh.Trimesh:
    """Refuse a membrane that is not one oriented, manifold sheet open at its base alone
    with outward normals: ValueError naming ``name`` and what is wrong. Returns the mesh."""
    validate_mesh(mesh, name)
    edges = np.sort(np.asarray(mesh.edges), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    if counts.max() > 2:
        raise ValueError(f"{name}: non-manifold, {int((counts > 2).sum())} edges are shared by 3 faces or more")
    if not mesh.is_winding_consistent:
        raise ValueError(f"{name}: its faces' normals are inconsistent (neighbouring faces wound opposite ways)")
    loop = base_loop(mesh, name)
    # Close the base with a fan to the loop's centre: the closed surface's volume is
    # positive when the normals point out.
    V = np.vstack([mesh.vertices, np.asarray(mesh.vertices)[loop].mean(axis=0)])
    k = len(V) - 1
    cap = np.c_[loop, np.roll(loop, -1), np.full(len(loop), k)]
    closed = trimesh.Trimesh(V, np.vstack([mesh.faces, cap]), process=False)
    if not closed.is_winding_consistent:  # the loop ran the other way round the base
        closed = trimesh.Trimesh(V, np.vstack([mesh.faces, cap[:, ::-1]]), process=False)
    volume = closed.volume
    if not np.isfinite(volume) or abs(volume) < 1e-12 * float(np.ptp(mesh.vertices, axis=0).max()) ** 3:
        raise ValueError(f"{name}: its base loop does not close it into a solid")
    if volume < 0:
        raise ValueError(f"{name}: its normals point inwards; flip its faces (trimesh: mesh.invert())")
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
