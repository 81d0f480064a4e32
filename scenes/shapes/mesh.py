"""The mesh family: a membrane read from any mesh file (STL, OBJ, PLY, ...), in metres, and
the checks that make a mesh a membrane.

A spec names the file (``mesh_path``) in ``mesh_units`` and places it in the camera frame
by ``mesh_transform`` (:data:`TABLE_KEYS`; the camera's ``offset_m`` and ``tilt_rad``
seat generated membranes only). Its core is derived by offsetting the membrane inwards
by ``thickness``, or given as a mesh of its own (``core_mesh_path``, in the same units and
frame); ``scenes.body`` measures either. A file is refused unless it is one oriented,
manifold sheet open at its base alone, normals out (:func:`check_membrane`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from .interface import needs_thickness, no_params, tip_and_body

NAME = "mesh"
TABLE_KEYS = ("mesh_path", "core_mesh_path", "mesh_transform")
SIZE_FROM = "its mesh_path"
CORE_FROM = "thickness or core_mesh_path"
SEATED = False
FILLS_VIEW = False
PUBLISHED = False
REGIONS = ("tip", "body")
#: A mesh file has no parameters: nothing of its shape can be varied.
PARAMETERS = None

#: A mesh whose largest extent exceeds this (in the file's units) is not in metres: no
#: sensor is a metre across (the bound ``scenes.spec.MAX_SENSOR_SIZE_M`` puts on a spec's
#: lengths).
MM_SUSPICION_EXTENT = 1.0
#: Metres per unit of a mesh file.
UNIT_SCALE = {"m": 1.0, "mm": 1e-3}


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


def membrane_params(params, where: str) -> dict[str, float]:
    """None: a mesh's size is its file's."""
    return no_params(params, NAME, SIZE_FROM, where)


def check(membrane, where: str) -> None:
    """A mesh needs its file, and its elastomer's thickness or its core's mesh (not both)."""
    if not membrane.mesh_path:
        raise ValueError(f"{where}: shape = 'mesh' needs mesh_path")
    needs_thickness(membrane, where, core_mesh=True)


def tube(membrane) -> None:
    """None: ``scenes.body`` measures the core (derived, or given as a mesh)."""
    return None


def mesh(membrane) -> trimesh.Trimesh:
    """The membrane read from ``mesh_path`` in ``mesh_units``, placed in the camera frame by
    ``mesh_transform``, checked by :func:`check_membrane`."""
    out = load_mesh(membrane.mesh_path, units=membrane.mesh_units)
    if membrane.mesh_transform is not None:
        out.apply_transform(np.reshape(membrane.mesh_transform, (4, 4)))
    return check_membrane(out, f"membrane {membrane.mesh_path}")


def regions(membrane, points: np.ndarray, inside: np.ndarray) -> dict[str, np.ndarray]:
    """The tip (the top share of the visible membrane along the axis) and the body."""
    return tip_and_body(points, inside)
