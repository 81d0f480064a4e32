"""Pinhole camera model: projection, back-projection and the no-contact depth D_ref."""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import trimesh

from .spec import CameraSpec, SensorSpec

#: The contact threshold, metres: a pixel whose depth lies below the no-contact depth
#: D_ref by more than this is in contact (or moved, for a deformed surface); smaller
#: differences are rasterisation noise (MuJoCo's no-contact capture matches the ray-cast
#: D_ref to 3e-9 m RMS, 3e-8 m at worst). The one threshold of both renderers and the studies.
CONTACT_EPS_M = 1e-6


@dataclass(frozen=True)
class Camera:
    """Pinhole camera at the origin, looking along +z (x right, y down), planar z-depth.

    Pixel (u, v) has its centre at integer coordinates; the principal point of the
    published GelTip camera is ((W - 1) / 2, (H - 1) / 2) = (319.5, 239.5). The image
    circle (the sensor's aperture) has its own centre: the published images centre it on
    pixel (320, 240).
    """

    width: int  # px
    height: int  # px
    f: float  # px, focal length (square pixels)
    cx: float  # px
    cy: float  # px
    mask_radius_px: float  # px, radius of the sensor's image circle
    mask_cx: float | None = None  # px, centre of the image circle; None: cx
    mask_cy: float | None = None  # px; None: cy

    @classmethod
    def from_spec(cls, spec: CameraSpec | SensorSpec) -> "Camera":
        if isinstance(spec, SensorSpec):
            spec = spec.camera
        f = (spec.height / 2.0) / math.tan(spec.fov_y / 2.0)
        return cls(
            width=spec.width,
            height=spec.height,
            f=f,
            cx=(spec.width - 1) / 2.0,
            cy=(spec.height - 1) / 2.0,
            mask_radius_px=spec.mask_radius_px,
            mask_cx=spec.mask_center_px[0] if spec.mask_center_px else None,
            mask_cy=spec.mask_center_px[1] if spec.mask_center_px else None,
        )

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W)."""
        return (self.height, self.width)

    def scaled(self, width: int, height: int) -> "Camera":
        """The same camera at another resolution (same field of view)."""
        s = height / self.height
        scale = (lambda m: None if m is None else (m + 0.5) * s - 0.5)  # pixel centres
        return Camera(width, height, self.f * s, (width - 1) / 2.0, (height - 1) / 2.0, self.mask_radius_px * s,
                      scale(self.mask_cx), scale(self.mask_cy))

    @cached_property
    def rays(self) -> np.ndarray:
        """(H, W, 3) float64: per-pixel ray directions with z = 1, so P = depth * ray."""
        v, u = np.mgrid[0 : self.height, 0 : self.width].astype(np.float64)
        rays = np.stack([(u - self.cx) / self.f, (v - self.cy) / self.f, np.ones_like(u)], axis=-1)
        rays.setflags(write=False)
        return rays

    @cached_property
    def rays_channels_first(self) -> np.ndarray:
        """(3, H, W) float32: the same rays, one contiguous plane per component."""
        rays = np.ascontiguousarray(self.rays.transpose(2, 0, 1), dtype=np.float32)
        rays.setflags(write=False)
        return rays

    @cached_property
    def mask(self) -> np.ndarray:
        """(H, W) bool: inside the sensor's image circle."""
        v, u = np.mgrid[0 : self.height, 0 : self.width]
        mx = self.cx if self.mask_cx is None else self.mask_cx
        my = self.cy if self.mask_cy is None else self.mask_cy
        m = (u - mx) ** 2 + (v - my) ** 2 <= self.mask_radius_px**2
        m.setflags(write=False)
        return m


def check_depth(depth, camera: Camera, name: str = "depth") -> np.ndarray:
    """Validate a depth map against a camera; returns it as float64.

    A depth map is (H, W) float, metres, planar z-depth, finite and > 0 everywhere.
    """
    if not isinstance(depth, np.ndarray):
        raise ValueError(f"{name} must be a numpy array, got {type(depth).__name__}")
    if depth.shape != camera.shape or depth.dtype.kind != "f":
        raise ValueError(
            f"{name} must be {camera.shape} float (metres), got {depth.shape} {depth.dtype}"
        )
    finite = np.isfinite(depth)
    if not finite.all():
        raise ValueError(f"{name} has {int((~finite).sum())} NaN or infinite pixels; expected finite metres")
    if depth.min() <= 0:
        raise ValueError(f"{name} must be > 0 m everywhere, got min {float(depth.min()):g}")
    if depth.max() > 10.0:
        raise ValueError(
            f"{name} max {float(depth.max()):g} is not a plausible sensor depth in metres "
            "(millimetres, or a far-plane value?)"
        )
    return depth


def project(points: np.ndarray, camera: Camera) -> np.ndarray:
    """Project camera-frame points to pixel coordinates.

    points : (..., 3) metres, z > 0.  Returns (..., 2) float (u, v) in px:
    u = f x / z + c_x, v = f y / z + c_y.
    """
    points = np.asarray(points, dtype=np.float64)
    if points.shape[-1] != 3:
        raise ValueError(f"points must be (..., 3), got {points.shape}")
    z = points[..., 2]
    return np.stack([camera.f * points[..., 0] / z + camera.cx, camera.f * points[..., 1] / z + camera.cy], axis=-1)


#: Samples of the table that inverts the radial lens polynomial (``undistorted_radius``).
LENS_TABLE_SAMPLES = 8192


def undistorted_radius(r_d: np.ndarray, k1: float, k2: float) -> np.ndarray:
    """Where a radially distorted point came from: the lens's one convention.

    A Brown-Conrady lens moves the pinhole point at normalised radius r_u (its distance to
    the principal point over f) to r_d = r_u (1 + k1 r_u^2 + k2 r_u^4): k1 > 0 is a
    pincushion, k1 < 0 a barrel (OpenCV's convention). This inverts it on the branch that
    rises from 0, by a table of the polynomial; radii beyond that branch's fold (a strong
    barrel reaches no further) are NaN: no ray lands there.

    r_d : array of radii >= 0, focal lengths.  Returns r_u, same shape.
    """
    r_d = np.asarray(r_d, dtype=np.float64)
    if k1 == 0 and k2 == 0:
        return r_d.copy()
    # The table reaches past the largest radius asked: r_u < r_d where the lens only
    # stretches; a barrel's r_u can be larger, so the table goes a few times further.
    top = 4.0 * max(float(np.nanmax(r_d, initial=0.0)), 1.0)
    r_u = np.linspace(0.0, top, LENS_TABLE_SAMPLES)
    table = r_u * (1.0 + k1 * r_u**2 + k2 * r_u**4)
    rising = np.diff(table) > 0
    end = len(r_u) if rising.all() else int(np.argmin(rising)) + 1
    return np.interp(r_d, table[:end], r_u[:end], right=np.nan)


def undistortion_stretch(r_d: np.ndarray, k1: float, k2: float) -> np.ndarray:
    """r_u / r_d (``undistorted_radius``): what a distorted pixel's offset from the
    principal point is multiplied by to reach its undistorted position; 1 at the centre,
    NaN past a barrel's fold."""
    r_d = np.asarray(r_d, dtype=np.float64)
    return np.divide(undistorted_radius(r_d, k1, k2), r_d, out=np.ones_like(r_d), where=r_d > 0)


def back_project(depth: np.ndarray, camera: Camera, channels_first: bool = False) -> np.ndarray:
    """Point cloud of a planar z-depth map: P = D (u - c_x, v - c_y, f) / f.

    depth : (H, W) float, metres.  Returns (H, W, 3) camera-frame points, metres, or
    (3, H, W) float32 with ``channels_first`` (one contiguous plane per component).
    """
    if depth.shape != camera.shape:
        raise ValueError(f"depth must be {camera.shape}, got {depth.shape}")
    if channels_first:
        return depth * camera.rays_channels_first
    return depth[..., None] * camera.rays.astype(depth.dtype, copy=False)


@dataclass(frozen=True)
class SurfaceSamples:
    """Where each camera pixel's ray first meets the membrane.

    pixels : (K, 2) int (row, col) of the pixels that hit, inside the mask.
    points : (K, 3) float64 metres, hit points in the camera frame.
    faces : (K,) int, hit face index.
    bary : (K, 3) float64, barycentric coordinates of the hit in its face.
    normals : (K, 3) float64, unit outward surface normals (interpolated vertex normals).
    """

    shape: tuple[int, int]
    pixels: np.ndarray
    points: np.ndarray
    faces: np.ndarray
    bary: np.ndarray
    normals: np.ndarray

    @classmethod
    def on_mesh(
        cls, mesh: trimesh.Trimesh, points: np.ndarray, faces: np.ndarray, pixels: np.ndarray, shape: tuple[int, int]
    ) -> "SurfaceSamples":
        """Samples at points known to lie on given faces: barycentrics and normals."""
        bary = trimesh.triangles.points_to_barycentric(mesh.triangles[faces], points)
        bary = np.clip(bary, 0.0, 1.0)
        bary /= bary.sum(axis=1, keepdims=True)
        corner = np.asarray(mesh.vertex_normals)[mesh.faces[faces]]  # (K, 3, 3)
        normals = (corner * bary[..., None]).sum(axis=1)
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        return cls(tuple(shape), pixels, points, faces, bary, normals)

    @classmethod
    def at_points(cls, mesh: trimesh.Trimesh, points: np.ndarray) -> "SurfaceSamples":
        """Samples at the mesh points closest to arbitrary points (K, 3), as a 1 x K image."""
        # trimesh's closest-point search has absolute tolerances that misfire on metre-
        # scale meshes (0.35 mm off at the GelTip's pole), so search in millimetres.
        scaled = trimesh.Trimesh(np.asarray(mesh.vertices) * 1e3, mesh.faces, process=False)
        closest, _, faces = trimesh.proximity.closest_point(scaled, np.asarray(points, dtype=np.float64) * 1e3)
        closest = closest * 1e-3
        k = len(closest)
        pixels = np.stack([np.zeros(k, int), np.arange(k)], axis=1)
        return cls.on_mesh(mesh, closest, faces, pixels, (1, k))

    def scatter(self, values: np.ndarray, fill: float = 0.0) -> np.ndarray:
        """Put per-sample values (K, ...) back into an image (H, W, ...)."""
        out = np.full(self.shape + values.shape[1:], fill, dtype=values.dtype)
        out[self.pixels[:, 0], self.pixels[:, 1]] = values
        return out

    def interpolate(self, mesh: trimesh.Trimesh, vertex_values: np.ndarray) -> np.ndarray:
        """Barycentric interpolation of per-vertex values (N, ...) at the samples."""
        corner = vertex_values[mesh.faces[self.faces]]  # (K, 3, ...)
        w = self.bary.reshape(self.bary.shape + (1,) * (corner.ndim - 2))
        return (corner * w).sum(axis=1)


def cast_rays(mesh: trimesh.Trimesh, camera: Camera, whole_frame: bool = False) -> SurfaceSamples:
    """Cast one ray per pixel at the mesh (first hit): inside the image circle, or on
    the whole frame.

    Uses trimesh's ray engine (Embree through embreex when installed).
    """
    rows, cols = np.nonzero(np.ones(camera.shape, bool) if whole_frame else camera.mask)
    dirs = camera.rays[rows, cols]
    dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    origins = np.zeros_like(dirs)
    tri, ray, loc = mesh.ray.intersects_id(origins, dirs, multiple_hits=False, return_locations=True)
    order = np.argsort(ray)
    tri, ray, loc = tri[order], ray[order], np.asarray(loc)[order]
    pixels = np.stack([rows[ray], cols[ray]], axis=1)
    # Snap hits exactly onto the ray (Embree works in float32).
    t = np.einsum("ij,ij->i", loc, dirs[ray])
    return SurfaceSamples.on_mesh(mesh, dirs[ray] * t[:, None], tri, pixels, camera.shape)


def reference_depth(mesh: trimesh.Trimesh, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """No-contact depth map D_ref of a membrane mesh.

    The whole frame is cast, not only the image circle, so that the map stays smooth
    across the circle's edge (the Sobel normals there read pixels outside it).

    Returns
    -------
    depth : (H, W) float32, metres, planar z-depth; pixels without a hit hold the
        largest hit depth (so the map stays finite and positive).
    valid : (H, W) bool, pixels whose ray hit the membrane.
    """
    samples = cast_rays(mesh, camera, whole_frame=True)
    if len(samples.points) == 0:
        raise ValueError("no camera ray hits the membrane mesh; is it in the camera frame, in metres?")
    z = samples.points[:, 2]
    depth = samples.scatter(z.astype(np.float32), fill=float(z.max()))
    valid = samples.scatter(np.ones(len(z), bool), fill=False)
    return depth, valid
