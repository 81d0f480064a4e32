"""A contact given as an indenter mesh and a pose, turned into the contact depth map.

The in-sensor camera sees the indenter where it is inside the membrane, so the contact is
the same depth map the fast path takes, D = min(D_ref, z of the indenter's first hit)
(:func:`scenes.contact.indenter_depth`), and :func:`pbr_tactile.membrane.elastomer`
rebuilds the deformed membrane from it::

    solid = elastomer(membrane, spec, camera, contact_depth(shape, camera, ref, pose), ref)
"""

from __future__ import annotations

import warnings

import numpy as np
import trimesh

from scenes.camera import CONTACT_EPS_M, Camera, check_depth, reference_depth
from scenes.contact import indenter_depth
from scenes.elastic import LAYER_EDGE_M
from scenes.shapes.mesh import validate_mesh
from scenes.indenters import MAX_INDENTER_EXTENT_M, check_closed
from scenes.spec import MAX_SENSOR_SIZE_M, SensorSpec

from .membrane import Elastomer, elastomer

#: Largest |R^T R - I| entry of a rigid pose: a rotation typed to four decimals passes.
ROTATION_TOLERANCE = 1e-4


def check_pose(pose, name: str = "pose") -> np.ndarray:
    """Validate a rigid pose: a (4, 4) homogeneous transform, metres, finite, det R = +1.

    Returns it as float64. Scaling, shear, reflection and a projective last row are
    refused (convert units in the mesh, not the pose).
    """
    try:
        pose = np.asarray(pose, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a (4, 4) array of numbers, got {type(pose).__name__}") from None
    if pose.shape != (4, 4):
        raise ValueError(f"{name} must be a (4, 4) homogeneous transform, got shape {pose.shape}")
    if not np.isfinite(pose).all():
        raise ValueError(f"{name} has {int((~np.isfinite(pose)).sum())} NaN or infinite entries")
    if not np.array_equal(pose[3], [0.0, 0.0, 0.0, 1.0]):
        raise ValueError(f"{name} last row must be [0, 0, 0, 1], got {pose[3].tolist()}")
    R, t = pose[:3, :3], pose[:3, 3]
    off = float(np.abs(R.T @ R - np.eye(3)).max())
    if off > ROTATION_TOLERANCE:
        raise ValueError(
            f"{name} must be rigid: R^T R differs from I by {off:.3g} (tolerance {ROTATION_TOLERANCE:g}); "
            "scale or shear the mesh, not the pose"
        )
    det = float(np.linalg.det(R))
    if det < 0:
        raise ValueError(f"{name} rotation must have det +1, got {det:.3g} (a reflection turns the indenter inside out)")
    if np.linalg.norm(t) > MAX_SENSOR_SIZE_M:
        raise ValueError(
            f"{name} translation {np.linalg.norm(t):g} is farther than {MAX_SENSOR_SIZE_M:g} m from the camera; "
            "it looks like millimetres, but metres were expected"
        )
    return pose


def check_indenter(shape, name: str = "indenter") -> trimesh.Trimesh:
    """Validate an indenter mesh: faces, finite vertices, metres, watertight, consistently wound."""
    if not isinstance(shape, trimesh.Trimesh):
        raise TypeError(f"{name} must be a trimesh.Trimesh, got {type(shape).__name__}")
    vertices = np.asarray(shape.vertices, dtype=np.float64)
    if len(vertices) and np.isfinite(vertices).all():  # otherwise validate_mesh names the bad vertices
        extent = float(np.max(vertices.max(axis=0) - vertices.min(axis=0)))
        if extent > MAX_INDENTER_EXTENT_M:
            raise ValueError(
                f"{name}: extent {extent:g} m is larger than {MAX_INDENTER_EXTENT_M:g} m for an indenter; "
                "it looks like millimetres, but metres were expected"
            )
    validate_mesh(shape, name=name)
    check_closed(shape, name)
    return shape


def contact_depth(
    shape: trimesh.Trimesh, camera: Camera, ref_depth: np.ndarray, pose: np.ndarray | None = None
) -> np.ndarray:
    """Contact depth map of a rigid indenter: D = min(D_ref, indenter depth).

    Parameters
    ----------
    shape : closed indenter mesh, metres; ``trimesh.primitives.Sphere`` is intersected exactly.
    ref_depth : (H, W) float, metres, the no-contact depth D_ref.
    pose : (4, 4) float, the rigid transform taking ``shape`` to the sensor (camera)
        frame, metres; None when ``shape`` is already posed there.

    Returns
    -------
    (H, W) float32, metres, planar z-depth, as :func:`scenes.contact.press` gives.

    Warns when the indenter does not reach the membrane (D = D_ref).
    """
    check_depth(ref_depth, camera, "ref_depth")
    posed = check_indenter(shape).copy()
    if pose is not None:
        posed.apply_transform(check_pose(pose))
    if posed.contains(np.zeros((1, 3)))[0]:
        raise ValueError("the posed indenter contains the camera (the sensor frame's origin); check the pose's frame")
    depth = np.minimum(ref_depth, indenter_depth(posed, camera)).astype(np.float32)
    if not (depth < ref_depth - CONTACT_EPS_M).any():
        warnings.warn("the indenter does not reach the membrane: the depth map is D_ref (no contact)", stacklevel=2)
    return depth


def contact_elastomer(
    membrane: trimesh.Trimesh,
    spec: SensorSpec,
    camera: Camera,
    shape: trimesh.Trimesh,
    pose: np.ndarray | None = None,
    ref_depth: np.ndarray | None = None,
    edge: float = LAYER_EDGE_M,
) -> Elastomer:
    """The elastomer solid dented by an indenter mesh at a pose (see :func:`contact_depth`).

    ref_depth : (H, W) float, metres, D_ref (None: ray cast from ``membrane``).
    """
    if ref_depth is None:
        ref_depth = reference_depth(membrane, camera)[0]
    depth = contact_depth(shape, camera, ref_depth, pose)
    return elastomer(membrane, spec, camera, depth, ref_depth, edge=edge)
