"""Membrane geometry: meshes built from the sensor spec or loaded from any file."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import trimesh

from .spec import MAX_SENSOR_SIZE_M, MembraneSpec, SensorSpec

#: A mesh whose largest extent exceeds this (in the file's units) is not in metres.
MM_SUSPICION_EXTENT = MAX_SENSOR_SIZE_M


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
    """The membrane of a sensor spec in the camera frame: generated (and seated as the
    camera spec says, ``CameraSpec.tube_to_camera``), or loaded from ``mesh_path``."""
    if spec.membrane.shape == "capsule":
        mesh = capsule_mesh(spec.membrane)
        pose = spec.camera.tube_to_camera()
        if not np.array_equal(pose, np.eye(4)):
            mesh.apply_transform(pose)
        return mesh
    return load_mesh(spec.membrane.mesh_path)


def mesh_digest(mesh: trimesh.Trimesh) -> str:
    """Stable hash of vertices and faces, for cache keys."""
    import hashlib

    h = hashlib.sha256()
    h.update(np.ascontiguousarray(mesh.vertices, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(mesh.faces, dtype=np.int64).tobytes())
    return h.hexdigest()[:16]
