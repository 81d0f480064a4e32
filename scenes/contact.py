"""Analytic contacts: depth maps of a rigid shape pressed into the membrane.

The indentation is geometric, as in the published MuJoCo set-up: where the indenter is
inside the membrane, the in-sensor camera sees the indenter's surface instead of the
membrane, so D = min(D_ref, z of the indenter's first hit).
"""

from __future__ import annotations

import numpy as np
import trimesh

from .camera import Camera, check_depth

#: A contact point farther than this from the membrane is not on it.
ON_SURFACE_TOLERANCE_M = 0.5e-3
#: Deepest indentation accepted, metres (the membrane is about 2.5 mm thick; the
#: published sphere contacts went much deeper, so this only stops unit mistakes).
MAX_INDENTATION_M = 0.015


def surface_point(mesh: trimesh.Trimesh, camera: Camera, pixel: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
    """The membrane point seen at a pixel and its unit outward normal.

    pixel : (u, v) in px (column, row).  Returns point (3,) metres and normal (3,).
    """
    u, v = (float(p) for p in pixel)
    if not (0 <= u <= camera.width - 1 and 0 <= v <= camera.height - 1):
        raise ValueError(f"pixel must lie in the {camera.width}x{camera.height} image, got {pixel}")
    x, y = camera.slopes(np.array(u), np.array(v))
    if not np.isfinite(x):
        raise ValueError(f"no ray of the camera's lens lands at pixel {pixel}")
    d = np.array([float(x), float(y), 1.0])
    d /= np.linalg.norm(d)
    tri, _, loc = mesh.ray.intersects_id(np.zeros((1, 3)), d[None], multiple_hits=False, return_locations=True)
    if len(tri) == 0:
        raise ValueError(f"the camera ray through pixel {pixel} misses the membrane")
    point = d * float(np.dot(loc[0], d))
    bary = np.clip(trimesh.triangles.points_to_barycentric(mesh.triangles[tri[:1]], point[None])[0], 0, 1)
    normal = (np.asarray(mesh.vertex_normals)[mesh.faces[tri[0]]] * (bary / bary.sum())[:, None]).sum(axis=0)
    return point, normal / np.linalg.norm(normal)


def pose_indenter(
    shape: trimesh.Trimesh,
    point: np.ndarray,
    normal: np.ndarray,
    depth: float,
    spin: float = 0.0,
) -> trimesh.Trimesh:
    """Place a shape so that it presses ``depth`` metres into the membrane at ``point``.

    The shape's local +z axis (the side its feature is on) is turned to face the
    membrane (-normal), spun by ``spin`` radians about it, and moved along the normal
    until its deepest point lies ``depth`` below the surface point, with the centre of
    its bounding box on the normal line through the point.
    """
    point = np.asarray(point, dtype=np.float64).reshape(3)
    normal = np.asarray(normal, dtype=np.float64).reshape(3)
    if not np.all(np.isfinite(point)) or not np.all(np.isfinite(normal)):
        raise ValueError("point and normal must be finite")
    n_len = np.linalg.norm(normal)
    if abs(n_len - 1.0) > 1e-6:
        raise ValueError(f"normal must be a unit vector, got length {n_len:g}")
    if not (0.0 <= depth <= MAX_INDENTATION_M):
        raise ValueError(f"depth must be in [0, {MAX_INDENTATION_M}] m, got {depth!r}")
    rot = trimesh.geometry.align_vectors([0.0, 0.0, 1.0], -normal)
    rot = rot @ trimesh.transformations.rotation_matrix(spin, [0.0, 0.0, 1.0])
    posed = shape.copy()
    posed.apply_transform(rot)
    v = np.asarray(posed.vertices)
    centre = 0.5 * (v.min(axis=0) + v.max(axis=0))
    lateral = point - centre
    lateral -= np.dot(lateral, normal) * normal
    along = (np.dot(point, normal) - depth) - (v @ normal).min()
    posed.apply_translation(lateral + along * normal)
    return posed


def indenter_depth(indenter: trimesh.Trimesh, camera: Camera) -> np.ndarray:
    """z of the first hit of each pixel's ray with the indenter; inf where it misses.

    Returns (H, W) float64, metres.
    """
    if isinstance(indenter, trimesh.primitives.Sphere):
        return sphere_depth(np.asarray(indenter.primitive.center), float(indenter.primitive.radius), camera)
    rows, cols = np.nonzero(camera.mask)
    dirs = camera.rays[rows, cols]
    dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    tri, ray, loc = indenter.ray.intersects_id(
        np.zeros_like(dirs), dirs, multiple_hits=False, return_locations=True
    )
    out = np.full(camera.shape, np.inf)
    out[rows[ray], cols[ray]] = np.einsum("ij,ij->i", loc, dirs[ray]) * dirs[ray, 2]
    return out


def sphere_depth(centre: np.ndarray, radius: float, camera: Camera) -> np.ndarray:
    """Exact z of the first ray hit with a sphere; inf where rays miss. (H, W) metres."""
    d = camera.rays / np.linalg.norm(camera.rays, axis=-1, keepdims=True)
    b = d @ centre
    disc = b**2 - (centre @ centre - radius**2)
    t = b - np.sqrt(np.where(disc >= 0, disc, np.nan))
    t = np.where((disc >= 0) & (t > 0), t, np.inf)
    return np.where(np.isfinite(t), t * d[..., 2], np.inf)


def press(
    ref_depth: np.ndarray,
    camera: Camera,
    mesh: trimesh.Trimesh,
    shape: trimesh.Trimesh,
    pixel: tuple[float, float],
    depth: float,
    spin: float = 0.0,
) -> np.ndarray:
    """Depth map of ``shape`` pressed ``depth`` metres into the membrane at a pixel.

    Parameters
    ----------
    ref_depth : (H, W) float, metres, the no-contact depth D_ref.
    shape : any trimesh (``trimesh.primitives.Sphere`` is intersected exactly).
    pixel : (u, v), where the camera sees the contact point.

    Returns
    -------
    (H, W) float32, metres: min(D_ref, indenter depth).
    """
    check_depth(ref_depth, camera, "ref_depth")
    if not isinstance(shape, trimesh.Trimesh) or len(shape.faces) == 0:
        raise ValueError(f"shape must be a trimesh.Trimesh with faces, got {type(shape).__name__}")
    point, normal = surface_point(mesh, camera, pixel)
    posed = pose_indenter(shape, point, normal, depth, spin)
    if isinstance(shape, trimesh.primitives.Sphere):
        centre = point - normal * (depth - shape.primitive.radius)
        posed = trimesh.primitives.Sphere(radius=shape.primitive.radius, center=centre)
    return np.minimum(ref_depth, indenter_depth(posed, camera)).astype(np.float32)
