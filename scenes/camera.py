"""Pinhole camera model: projection, back-projection and the no-contact depth D_ref."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import trimesh

#: The contact threshold, metres: a pixel whose depth lies below the no-contact depth
#: D_ref by more than this is in contact (or moved, for a deformed surface); smaller
#: differences are rasterisation noise (MuJoCo's no-contact capture matches the ray-cast
#: D_ref to 3e-9 m RMS, 3e-8 m at worst). The one threshold of both renderers and the studies.
CONTACT_EPS_M = 1e-6


@dataclass(frozen=True)
class Camera:
    """Central camera at the origin, looking along +z (x right, y down), planar z-depth.

    A ray at angle theta from the axis lands ``f * lens_radius(theta, k1, k2,
    projection)`` pixels from the principal point (cx, cy) (see PROJECTIONS); with no
    distortion and the pinhole projection this is the pinhole u = f x / z + cx.

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
    k1: float = 0.0  # radial distortion (see lens_radius)
    k2: float = 0.0
    projection: str = "pinhole"

    @classmethod
    def from_spec(cls, spec) -> "Camera":
        """The spec's camera (a ``scenes.spec.CameraSpec``, or a ``SensorSpec``'s): its focal
        length puts the ray at fov_y / 2 from the axis at half the frame's height from the
        principal point."""
        spec = getattr(spec, "camera", spec)  # a SensorSpec's CameraSpec
        k1, k2 = spec.distortion
        f = (spec.height / 2.0) / float(lens_radius(spec.fov_y / 2.0, k1, k2, spec.projection))
        cx, cy = spec.principal_point_px or ((spec.width - 1) / 2.0, (spec.height - 1) / 2.0)
        return cls(
            width=spec.width,
            height=spec.height,
            f=f,
            cx=cx,
            cy=cy,
            mask_radius_px=spec.mask_radius_px,
            mask_cx=spec.mask_center_px[0] if spec.mask_center_px else None,
            mask_cy=spec.mask_center_px[1] if spec.mask_center_px else None,
            k1=k1,
            k2=k2,
            projection=spec.projection,
        )

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W)."""
        return (self.height, self.width)

    @property
    def is_pinhole(self) -> bool:
        """A distortion-free pinhole (what Mitsuba's and MuJoCo's cameras are)."""
        return self.projection == "pinhole" and self.k1 == 0 and self.k2 == 0

    def scaled(self, width: int, height: int) -> "Camera":
        """The same camera at another resolution (same field of view and lens)."""
        s = height / self.height
        scale = (lambda m: None if m is None else (m + 0.5) * s - 0.5)  # pixel centres
        return dataclasses.replace(self, width=width, height=height, f=self.f * s, cx=scale(self.cx),
                                   cy=scale(self.cy), mask_radius_px=self.mask_radius_px * s,
                                   mask_cx=scale(self.mask_cx), mask_cy=scale(self.mask_cy))

    def slopes(self, u: np.ndarray | None = None, v: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(x / z, y / z) of the rays seen at pixels (u, v) (default: every pixel, (H, W)
        each); NaN where no ray lands (past a barrel's fold)."""
        if u is None:
            v, u = np.mgrid[0 : self.height, 0 : self.width].astype(np.float64)
        xd, yd = (np.asarray(u, np.float64) - self.cx) / self.f, (np.asarray(v, np.float64) - self.cy) / self.f
        if self.is_pinhole:
            return xd, yd
        stretch = undistortion_stretch(np.hypot(xd, yd), self.k1, self.k2, self.projection)
        return xd * stretch, yd * stretch

    @cached_property
    def rays(self) -> np.ndarray:
        """(H, W, 3) float64: per-pixel ray directions with z = 1, so P = depth * ray.
        Pixels that no ray reaches (past a strong barrel's fold, outside the image circle)
        look along the last ray that lands, so that every pixel stays finite."""
        x, y = self.slopes()
        lost = ~np.isfinite(x)
        if lost.any():
            v, u = np.nonzero(lost)
            xd, yd = (u - self.cx) / self.f, (v - self.cy) / self.f
            r = np.hypot(xd, yd)
            top = math.tan(float(lens_table(self.k1, self.k2, self.projection, float(r.max()))[1][-1]))
            x[lost], y[lost] = xd / r * top, yd / r * top
        rays = np.stack([x, y, np.ones_like(x)], axis=-1)
        rays.setflags(write=False)
        return rays

    @cached_property
    def rays_channels_first(self) -> np.ndarray:
        """(3, H, W) float32: the same rays, one contiguous plane per component."""
        rays = np.ascontiguousarray(self.rays.transpose(2, 0, 1), dtype=np.float32)
        rays.setflags(write=False)
        return rays

    def pinhole_cover(self, margin_px: float = 2.0) -> "Camera":
        """A distortion-free pinhole of this camera's size, principal point at the frame's
        centre, whose view holds the ray of every pixel of this camera's image circle
        (within ``margin_px`` of the frame): what Mitsuba and MuJoCo render before
        ``lens_resample`` turns it into this camera's image. Itself for a centred pinhole;
        otherwise its focal length is the largest that covers, at most this camera's."""
        centre = ((self.width - 1) / 2.0, (self.height - 1) / 2.0)
        if self.is_pinhole and (self.cx, self.cy) == centre:
            return self
        x, y = self.slopes()
        seen = self.mask & np.isfinite(x)
        if not seen.any():
            raise ValueError("no ray lands inside the camera's image circle: check its lens and circle")
        x, y = x[seen], y[seen]
        half_w, half_h = centre[0] - margin_px, centre[1] - margin_px
        f = min(self.f, half_w / max(float(np.abs(x).max()), 1e-12), half_h / max(float(np.abs(y).max()), 1e-12))
        return Camera(self.width, self.height, f, centre[0], centre[1], self.mask_radius_px, self.mask_cx, self.mask_cy)

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
    """Project camera-frame points to pixel coordinates through the camera's lens.

    points : (..., 3) metres, z > 0.  Returns (..., 2) float (u, v) in px; for a
    distortion-free pinhole u = f x / z + c_x, v = f y / z + c_y.
    """
    points = np.asarray(points, dtype=np.float64)
    if points.shape[-1] != 3:
        raise ValueError(f"points must be (..., 3), got {points.shape}")
    x, y = points[..., 0] / points[..., 2], points[..., 1] / points[..., 2]
    if not camera.is_pinhole:
        r = np.hypot(x, y)
        r_d = lens_radius(np.arctan(r), camera.k1, camera.k2, camera.projection)
        stretch = np.divide(r_d, r, out=np.ones_like(r), where=r > 0)
        x, y = x * stretch, y * stretch
    return np.stack([camera.f * x + camera.cx, camera.f * y + camera.cy], axis=-1)


#: Samples of the table that inverts a lens' radial mapping (``lens_angle``).
LENS_TABLE_SAMPLES = 16384
#: The lens' projections: where a ray at angle theta from the axis lands, r_d / f =
#: b (1 + k1 b^2 + k2 b^4) with b = tan(theta) (a pinhole with Brown-Conrady distortion,
#: OpenCV's convention) or b = theta (an equidistant fisheye with Kannala-Brandt's
#: polynomial, OpenCV's fisheye model): the one convention of both renderers, the depth
#: camera, the calibration and the diagnosis's catalogue.
PROJECTIONS = ("pinhole", "fisheye")


def lens_radius(theta: np.ndarray, k1: float = 0.0, k2: float = 0.0, projection: str = "pinhole") -> np.ndarray:
    """r_d / f: where a ray at ``theta`` rad from the optical axis lands, in focal lengths
    from the principal point (see PROJECTIONS)."""
    if projection not in PROJECTIONS:
        raise ValueError(f"projection must be one of {PROJECTIONS}, got {projection!r}")
    theta = np.asarray(theta, np.float64)
    b = np.tan(theta) if projection == "pinhole" else theta
    return b * (1.0 + k1 * b**2 + k2 * b**4)


def lens_table(k1: float = 0.0, k2: float = 0.0, projection: str = "pinhole", r_max: float = 1.0
               ) -> tuple[np.ndarray, np.ndarray]:
    """(r_d, theta): ``lens_radius`` tabled on the branch that rises from the axis, to
    its fold (a strong barrel reaches no further), to 90 degrees, or (a pinhole, whose
    radius runs to infinity) well past ``r_max`` focal lengths."""
    top = math.pi / 2 * (1 - 1e-9)
    if projection == "pinhole":
        top = math.atan(8.0 * max(r_max, 1.0))
    theta = np.linspace(0.0, top, LENS_TABLE_SAMPLES)
    table = lens_radius(theta, k1, k2, projection)
    rising = np.diff(table) > 0
    end = len(theta) if rising.all() else int(np.argmin(rising)) + 1
    return table[:end], theta[:end]


def lens_angle(r_d: np.ndarray, k1: float = 0.0, k2: float = 0.0, projection: str = "pinhole") -> np.ndarray:
    """The inverse of ``lens_radius`` on the branch that rises from the axis
    (``lens_table``): the angle (rad) of the ray seen at r_d focal lengths from the
    principal point; NaN beyond that branch, where no ray lands."""
    r_d = np.asarray(r_d, np.float64)
    if projection == "pinhole" and k1 == 0 and k2 == 0:
        return np.arctan(r_d)
    table, theta = lens_table(k1, k2, projection, float(np.nanmax(r_d, initial=0.0)))
    return np.interp(r_d, table, theta, right=np.nan)


def undistorted_radius(r_d: np.ndarray, k1: float, k2: float, projection: str = "pinhole") -> np.ndarray:
    """Where a radially distorted point came from: the pinhole radius r_u = tan(theta)
    (focal lengths) of the ray seen at r_d (``lens_angle``); k1 > 0 is a pincushion, k1 < 0
    a barrel. NaN where no ray lands.

    r_d : array of radii >= 0, focal lengths.  Returns r_u, same shape.
    """
    r_d = np.asarray(r_d, dtype=np.float64)
    if projection == "pinhole" and k1 == 0 and k2 == 0:
        return r_d.copy()
    return np.tan(lens_angle(r_d, k1, k2, projection))


def undistortion_stretch(r_d: np.ndarray, k1: float, k2: float, projection: str = "pinhole") -> np.ndarray:
    """r_u / r_d (``undistorted_radius``): what a distorted pixel's offset from the
    principal point is multiplied by to reach its undistorted position; at the centre its
    limit, NaN past a barrel's fold."""
    r_d = np.asarray(r_d, dtype=np.float64)
    return np.divide(undistorted_radius(r_d, k1, k2, projection), r_d, out=np.ones_like(r_d), where=r_d > 0)


def lens_resample(image: np.ndarray, lens: "Camera", pinhole: "Camera", order: int = 1,
                  mode: str = "nearest", cval: float = 0.0) -> np.ndarray:
    """The image ``lens`` sees, read from an image (H', W', ...) that the distortion-free
    pinhole camera ``pinhole`` (``Camera.pinhole_cover``) took from the same centre along
    the same axis: each of the lens' pixels is read where its ray lands in the pinhole's
    image (scipy.ndimage.map_coordinates, bilinear by default). Pixels whose ray the
    pinhole does not see take ``mode``'s fill; pixels no ray of the lens reaches (past a
    barrel's fold, outside the image circle) read along its last ray (``Camera.rays``), so
    the result stays finite."""
    from scipy import ndimage

    image = np.asarray(image)
    if image.shape[:2] != pinhole.shape:
        raise ValueError(f"image must be the pinhole camera's {pinhole.shape}, got {image.shape[:2]}")
    if order == 1 and mode == "nearest" and image.dtype.kind == "f":
        # The same bilinear read, planned once per pair of cameras: a capture reads
        # every frame through it.
        index, weight = _bilinear_plan(lens, pinhole)
        planes = np.ascontiguousarray(image.reshape(pinhole.height * pinhole.width, -1).T)  # (C, H*W)
        out = np.stack([sum(w * plane[i] for i, w in zip(index, weight)) for plane in planes], axis=-1)
        return out.reshape(lens.shape + image.shape[2:]).astype(image.dtype)
    rays = lens.rays
    coords = np.stack([pinhole.cy + pinhole.f * rays[..., 1], pinhole.cx + pinhole.f * rays[..., 0]])
    if image.ndim == 2:
        return ndimage.map_coordinates(image, coords, order=order, mode=mode, cval=cval).astype(image.dtype)
    flat = image.reshape(image.shape[:2] + (-1,))
    out = np.stack([ndimage.map_coordinates(flat[..., c], coords, order=order, mode=mode, cval=cval)
                    for c in range(flat.shape[-1])], axis=-1)
    return out.reshape(lens.shape + image.shape[2:]).astype(image.dtype)


def _bilinear_plan(lens: "Camera", pinhole: "Camera") -> tuple[np.ndarray, np.ndarray]:
    """Where ``lens_resample`` reads each of the lens' pixels in the pinhole's image, as
    scipy.ndimage.map_coordinates(order=1, mode="nearest") does: flat indices (4, H*W) of
    the four pixels round it and their weights (4, H*W) float32 (coordinates clamped to
    the frame). Kept on the lens, per pinhole."""
    plans = lens.__dict__.setdefault("_bilinear_plans", {})
    key = (pinhole.width, pinhole.height, pinhole.f, pinhole.cx, pinhole.cy)
    if key not in plans:
        rays = lens.rays.reshape(-1, 3)
        h, w = pinhole.shape
        r = np.clip(pinhole.cy + pinhole.f * rays[:, 1], 0.0, h - 1.0)
        c = np.clip(pinhole.cx + pinhole.f * rays[:, 0], 0.0, w - 1.0)
        r0 = np.minimum(np.floor(r), max(h - 2, 0)).astype(np.int64)
        c0 = np.minimum(np.floor(c), max(w - 2, 0)).astype(np.int64)
        fr, fc = r - r0, c - c0
        r1, c1 = np.minimum(r0 + 1, h - 1), np.minimum(c0 + 1, w - 1)
        index = np.stack([r0 * w + c0, r0 * w + c1, r1 * w + c0, r1 * w + c1])
        weight = np.stack([(1 - fr) * (1 - fc), (1 - fr) * fc, fr * (1 - fc), fr * fc]).astype(np.float32)
        for array in (index, weight):
            array.setflags(write=False)
        plans[key] = (index, weight)
    return plans[key]


def pinhole_view(image: np.ndarray, lens: "Camera", pinhole: "Camera", order: int = 0) -> np.ndarray:
    """The inverse of ``lens_resample``: an image (H, W) in ``lens``'s pixels read at
    each of ``pinhole``'s pixels, where its ray lands through the lens (nearest by
    default); 0 where it lands outside the lens' frame."""
    from scipy import ndimage

    image = np.asarray(image)
    if image.shape != lens.shape:
        raise ValueError(f"image must be the lens camera's {lens.shape}, got {image.shape}")
    uv = project(pinhole.rays, lens)
    coords = np.stack([np.nan_to_num(uv[..., 1], nan=-1e9), np.nan_to_num(uv[..., 0], nan=-1e9)])
    return ndimage.map_coordinates(image, coords, order=order, mode="constant", cval=0).astype(image.dtype)


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


#: A mesh vertex is hidden when the ray from the optical centre towards it meets the mesh
#: this much nearer (a share of its distance, and metres) than the vertex itself.
HIDDEN_SHARE, HIDDEN_M = 1e-4, 1e-6


def in_view(points: np.ndarray, camera: Camera) -> np.ndarray:
    """(N,) bool, whether camera-frame points (N, 3) lie ahead of the camera and project
    (to the nearest pixel) inside its image circle."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    out = np.zeros(len(points), bool)
    ahead = np.flatnonzero(points[:, 2] > 0)
    u, v = np.round(project(points[ahead], camera)).astype(np.int64).T
    frame = (u >= 0) & (u < camera.width) & (v >= 0) & (v < camera.height)
    out[ahead[frame]] = camera.mask[v[frame], u[frame]]
    return out


def unseen(mesh: trimesh.Trimesh, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Which vertices of a mesh (camera frame, metres) the camera does not see, and why
    (straight rays from the optical centre, as every renderer's depth map).

    Returns
    -------
    out_of_view : (V,) bool, behind the camera or outside its image circle.
    hidden : (V,) bool, in view but behind another part of the mesh.
    """
    V = np.asarray(mesh.vertices, dtype=np.float64)
    out = ~in_view(V, camera)
    look = np.flatnonzero(~out)
    distance = np.linalg.norm(V[look], axis=1)
    dirs = V[look] / distance[:, None]
    _, ray, loc = mesh.ray.intersects_id(np.zeros_like(dirs), dirs, multiple_hits=False, return_locations=True)
    first = np.full(len(look), np.inf)
    first[ray] = np.einsum("ij,ij->i", np.asarray(loc), dirs[ray])
    hidden = np.zeros(len(V), bool)
    hidden[look[first < distance * (1 - HIDDEN_SHARE) - HIDDEN_M]] = True
    return out, hidden


def view_angle(camera: Camera) -> float:
    """The widest cone about the optical axis the camera sees whole, rad: the least angle
    from the axis of a ray through a pixel outside the image circle or on the frame's edge."""
    edge = ~camera.mask
    edge[0, :] = edge[-1, :] = edge[:, 0] = edge[:, -1] = True
    rays = camera.rays[edge]
    return float(np.arctan2(np.hypot(rays[:, 0], rays[:, 1]), rays[:, 2]).min())
