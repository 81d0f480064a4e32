"""Surface normals of a back-projected depth map, from Sobel derivatives."""

from __future__ import annotations

import numpy as np
from scipy import ndimage


def normals(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals N of an organised point cloud, turned to face the camera.

    N = normalize(dP/du x dP/dv), with 3x3 Sobel derivatives along columns (u) and
    rows (v); the sign is chosen so that N . P < 0 (facing the camera at the origin).

    Parameters
    ----------
    points : (H, W, 3) float, metres, camera frame.

    Returns
    -------
    N : (H, W, 3) unit normals, same dtype; zero where undefined.
    valid : (H, W) bool, where the two derivatives span a plane.
    """
    if points.ndim != 3 or points.shape[2] != 3:
        raise ValueError(f"points must be (H, W, 3), got {points.shape}")
    du = np.stack([ndimage.sobel(points[..., c], axis=1) for c in range(3)], axis=-1)
    dv = np.stack([ndimage.sobel(points[..., c], axis=0) for c in range(3)], axis=-1)
    n = np.cross(du, dv)
    facing = np.einsum("...i,...i->...", n, points)
    norm = np.sqrt(np.einsum("...i,...i->...", n, n))
    valid = norm > 0
    scale = np.where(valid, -np.sign(facing) / np.where(valid, norm, 1), 0).astype(points.dtype)
    return n * scale[..., None], valid
