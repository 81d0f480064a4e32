"""Surface normals of a back-projected depth map, from Sobel derivatives."""

from __future__ import annotations

import numpy as np


def sobel_uv(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """3x3 Sobel derivatives of a planar point image along columns (u) and rows (v).

    points : (3, H, W).  Returns dP/du, dP/dv, each (3, H, W) (unnormalised Sobel, the
    border replicated as scipy.ndimage.sobel's default 'reflect' mode does for 3x3).
    """
    p = np.pad(points, ((0, 0), (1, 1), (1, 1)), mode="edge")
    dx = p[:, :, 2:] - p[:, :, :-2]
    du = dx[:, :-2] + 2 * dx[:, 1:-1] + dx[:, 2:]
    dy = p[:, 2:] - p[:, :-2]
    dv = dy[:, :, :-2] + 2 * dy[:, :, 1:-1] + dy[:, :, 2:]
    return du, dv


def normals(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals N of an organised point cloud, turned to face the camera.

    N = normalize(dP/du x dP/dv), with 3x3 Sobel derivatives along columns (u) and
    rows (v); the sign is chosen so that N . P < 0 (facing the camera at the origin).

    Parameters
    ----------
    points : (3, H, W) float, metres, camera frame, channel-first (each component a
        contiguous plane, which is what makes the fast path fast).

    Returns
    -------
    N : (3, H, W) unit normals, same dtype; zero where undefined.
    valid : (H, W) bool, where the two derivatives span a plane.
    """
    if points.ndim != 3 or points.shape[0] != 3:
        raise ValueError(f"points must be (3, H, W), got {points.shape}")
    du, dv = sobel_uv(points)
    n = np.stack(
        [du[1] * dv[2] - du[2] * dv[1], du[2] * dv[0] - du[0] * dv[2], du[0] * dv[1] - du[1] * dv[0]]
    )
    facing = n[0] * points[0] + n[1] * points[1] + n[2] * points[2]
    norm = np.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
    valid = norm > 0
    scale = np.where(valid, -np.sign(facing) / np.where(valid, norm, 1), 0).astype(points.dtype)
    n *= scale
    return n, valid
