"""The membrane as an elastic solid: a layer of the unit's thickness bonded to its rigid
support, pressed by a rigid indenter (the elastic model ``"bonded"``, scenes.elastic).

The surface's displacement u (m, into the membrane) of a linear elastic layer of
thickness h and Poisson's ratio nu, bonded to a rigid flat, under the frictionless normal
pressure p of a rigid indenter that reaches delta past the undeformed surface (a contact
depth map's D_ref - D), is u = G * p with the contact's conditions

    u >= delta,   p >= 0,   p (u - delta) = 0,

G the layer's Green's function in Fourier space (Carbone and Mangialardi, JMPS 2008,
eq. A.30, as ``ContactMechanics`` implements it; h = None: the elastic half-space's, so
that a ball makes Hertz's contact), solved by the constrained conjugate gradients of
Polonsky and Keer (``ContactMechanics.Optimization``). Unlike the layer model
(``scenes.elastic``, which decays over 0.29 h for an incompressible gel), the surface
outside the contact sinks as a solid's does, and an incompressible layer keeps its
volume: what the indenter pushes in rises round it.

It works on a square grid in the membrane's tangent plane at the contact (a pixel's size
there; ``BondedLayer`` maps a depth map's pixels onto it and back, on any membrane shape),
on a window PAD_THICKNESSES thicknesses wider than the contact on every side, so that the
periodic solution's neighbours do not reach it. The displacement does not depend on Young's modulus; the load does (``young_pa``).
``ContactMechanics`` is the optional ``contact`` extra, imported where a contact is solved.
"""

from __future__ import annotations

import functools
import hashlib
import math
from dataclasses import dataclass

import numpy as np

#: A layer's periodic window reaches this many of its thicknesses past the grid on every
#: side (its response decays over about one).
PAD_THICKNESSES = 4.0
#: Poisson's ratio is held below 0.5 by this much: at 0.5 the layer's uniform
#: compression is infinitely stiff (the Green's function's q = 0 term is 1 / (1 - 2 nu)).
#: At 1e-4 from it the layer's mean displacement stays within a few parts in 10^4 of
#: its absolute one; at 1e-7 the conjugate gradients did not converge in 3000 steps.
INCOMPRESSIBLE_MARGIN = 1e-4
#: The solver's convergence: penetration left in the contact, as a share of the deepest
#: reach, and force outside it, as a share of the load.
PENETRATION_SHARE = 1e-4
FORCE_SHARE = 1e-6


@dataclass
class Contact:
    """A solved contact: the surface's displacement ``u`` (H, W) m into the membrane, the
    pressure on each pixel ``pressure`` (H, W) Pa, the contact's pixels ``contact`` (H,
    W) bool, the indenter's load ``load_n`` N (at ``young_pa``) and the volume the
    surface lost, ``volume_m3``, over the whole solved window (an incompressible layer's
    is 0: its bulge gives back what the indenter pushes in)."""

    u: np.ndarray
    pressure: np.ndarray
    contact: np.ndarray
    load_n: float
    volume_m3: float = 0.0


def check_material(thickness_m: float | None, poisson: float) -> None:
    """Refuse a layer that is not a physical solid: a thickness not > 0 or a Poisson's
    ratio outside [0, 0.5]; one line naming the value."""
    if thickness_m is not None and not (math.isfinite(thickness_m) and thickness_m > 0):
        raise ValueError(f"the elastic layer's thickness must be a finite length > 0 m, got {thickness_m!r}")
    if not (math.isfinite(poisson) and 0.0 <= poisson <= 0.5):
        raise ValueError(f"the elastic layer's Poisson's ratio must lie in [0, 0.5], got {poisson!r}")


def solve(delta: np.ndarray, pixel_m: float, thickness_m: float | None, poisson: float,
          young_pa: float = 1.0) -> Contact:
    """The contact (module doc) of an indenter reaching ``delta`` (H, W) m past the
    undeformed surface (negative where it stays off it), on pixels ``pixel_m`` m square,
    of a layer ``thickness_m`` thick (None: a half-space) with Poisson's ratio ``poisson``
    and Young's modulus ``young_pa``. The whole (H, W) grid is solved (a layer's padded by
    PAD_THICKNESSES of its thickness); pass a window round the contact."""
    from ContactMechanics import FreeFFTElasticHalfSpace, PeriodicFFTElasticHalfSpace
    from ContactMechanics.Optimization.ConstrainedConjugateGradients import constrained_conjugate_gradients
    from ContactMechanics.Tools.Logger import quiet
    from SurfaceTopography import Topography

    delta = np.asarray(delta, np.float64)
    if delta.ndim != 2 or not np.all(np.isfinite(delta)):
        raise ValueError(f"an indenter's reach must be a finite (H, W) map, got shape {delta.shape}"
                         + ("" if delta.ndim != 2 else " with NaN or inf"))
    if not (math.isfinite(pixel_m) and pixel_m > 0):
        raise ValueError(f"a pixel's size must be > 0 m, got {pixel_m!r}")
    check_material(thickness_m, poisson)
    reach = float(delta.max())
    if reach <= 0:
        zero = np.zeros_like(delta)
        return Contact(zero, zero.copy(), np.zeros(delta.shape, bool), 0.0)
    h, w = delta.shape
    nu = min(poisson, 0.5 - INCOMPRESSIBLE_MARGIN)
    # the half-space's solver is not periodic (it pads itself); a layer's is
    pad = 0 if thickness_m is None else int(math.ceil(PAD_THICKNESSES * thickness_m / pixel_m))
    shape = (h + 2 * pad, w + 2 * pad)
    sizes = (shape[0] * pixel_m, shape[1] * pixel_m)
    # the padding is off the indenter: a reach further from the surface than any in the map
    heights = np.full(shape, min(float(delta.min()), 0.0) - reach)
    heights[pad:pad + h, pad:pad + w] = delta
    if thickness_m is None:
        substrate = FreeFFTElasticHalfSpace(shape, young_pa / (1 - nu * nu), sizes)
    else:
        substrate = PeriodicFFTElasticHalfSpace(shape, young_pa, sizes, thickness=thickness_m, poisson=nu)
    load_scale = young_pa * reach * pixel_m
    result = constrained_conjugate_gradients(substrate, Topography(heights, sizes), offset=0.0,
                                             pentol=PENETRATION_SHARE * reach, forcetol=FORCE_SHARE * load_scale,
                                             logger=quiet)
    if not result.success:
        raise RuntimeError(f"the elastic contact did not converge: {result.message}")
    full = np.asarray(result.x)[:shape[0], :shape[1]]
    force = np.asarray(result.jac)[:shape[0], :shape[1]]
    pressure = force[pad:pad + h, pad:pad + w] / (pixel_m * pixel_m)
    return Contact(full[pad:pad + h, pad:pad + w], pressure, pressure > 0, float(force.sum()),
                   float(full.sum()) * pixel_m * pixel_m)


#: The window solved reaches this many layer thicknesses past the indenter's footprint
#: (an incompressible layer's bulge lies within about two).
MARGIN_THICKNESSES = 3.0
#: A BondedLayer solves on a grid no finer than this, metres: a dent is smooth on the scale
#: of a tenth of a millimetre, and a 640x480 GelSight's 0.031 mm pixels made its solve 8
#: to 14 s (the pixels in contact are set on the indenter after the read-back either way).
GRID_STEP_M = 1e-4
#: Contacts a BondedLayer keeps, by their depth maps (the oldest dropped first).
MEMO_SIZE = 256


class BondedLayer:
    """The ``"bonded"`` elastic model on any membrane: the contact's surface from its depth
    map, as ``MembraneLayer.depth`` gives the layer model's (the fast path's renderer
    takes either). The thickness is the spec's elastomer's, the ratio its ``[elastic]
    poisson_ratio``; ``thickness`` and ``poisson`` replace them (a layer fitted to presses:
    ``phong_reference.elastic_fit``).

    The layer is taken flat in the membrane's tangent plane at the footprint's deepest
    point (a contact small beside the membrane's curvature: a 4 mm ball's on the GelTip's
    11.5 mm tube, or on a flat pad): each pixel of a window round the footprint is placed
    in that plane by its undeformed surface point, the indenter's reach along the plane's
    normal resampled on a square grid of the pixels' size there (at least GRID_STEP_M;
    linearly), the contact solved (:func:`solve`), and the surface's displacement u read
    back at each pixel (bilinearly) and moved along the normal: the pixel's depth falls by u over the cosine
    between its ray and the normal. Any camera the spec's rays describe works. The last
    MEMO_SIZE contacts are kept by their depth maps, so that a calibration that renders the
    same presses under many lights solves each dent once."""

    def __init__(self, spec, camera, thickness: float | None = None, poisson: float | None = None):
        self.thickness = spec.membrane.elastomer_thickness if thickness is None else float(thickness)
        self.poisson = spec.elastic.poisson_ratio if poisson is None else float(poisson)
        if self.thickness is None:
            raise ValueError(f"elastic model 'bonded' needs the elastomer's thickness; sensor {spec.name!r} states none "
                             "(its core is a mesh)")
        check_material(self.thickness, self.poisson)
        self.camera = camera
        self._memo: dict[bytes, tuple] = {}

    def solved(self, depth: np.ndarray, ref_depth: np.ndarray) -> tuple[Contact | None, tuple[slice, slice]]:
        """The contact of ``depth`` over ``ref_depth`` (H, W, m) on its window (rows,
        columns), None where nothing presses: its ``u`` (m, along the tangent plane's
        normal), ``pressure`` and ``contact`` read back at the window's pixels (a pixel is
        in contact where the nearest grid point is and the indenter reaches it), its load
        and volume the grid's."""
        return self._found(depth, ref_depth)[:2]

    def _found(self, depth, ref_depth):
        """(the contact, its window, each window pixel's ray-normal cosine, the deepest
        point's undeformed surface point (3,) m, the window's furthest surface point from
        it, m), solved once per depth map (MEMO_SIZE kept)."""
        depth, ref_depth = np.asarray(depth, np.float64), np.asarray(ref_depth, np.float64)
        if depth.shape != ref_depth.shape or depth.ndim != 2:
            raise ValueError(f"depth {depth.shape} and ref_depth {ref_depth.shape} must be the same (H, W)")
        if not (np.all(np.isfinite(depth)) and np.all(np.isfinite(ref_depth))):
            raise ValueError("depth and ref_depth must be finite (NaN or inf found)")
        reach = ref_depth - depth
        pressed = reach > 0
        if not pressed.any():
            return None, (slice(0, 0), slice(0, 0)), None, None, 0.0
        key = hashlib.sha1(reach.tobytes()).digest() + str(reach.shape).encode()
        if key not in self._memo:
            if len(self._memo) >= MEMO_SIZE:
                self._memo.pop(next(iter(self._memo)))
            self._memo[key] = self._solve(reach, pressed, ref_depth)
        return self._memo[key]

    def _solve(self, reach, pressed, ref_depth):
        from scipy.interpolate import RegularGridInterpolator, griddata

        H, W = reach.shape
        rays = np.asarray(self.camera.rays_channels_first, np.float64)  # planar z: P = D ray
        v, u = np.unravel_index(np.argmax(np.where(pressed, reach, -np.inf)), reach.shape)
        P = lambda r, c: ref_depth[r, c] * rays[:, r, c]  # noqa: E731
        du = P(v, min(u + 1, W - 1)) - P(v, max(u - 1, 0))
        dv = P(min(v + 1, H - 1), u) - P(max(v - 1, 0), u)
        n = np.cross(du, dv)
        n /= np.linalg.norm(n)
        if np.dot(n, P(v, u)) > 0:  # facing the camera: the way the indenter pushes the surface
            n = -n
        t1 = np.cross(n, [0.0, 1.0, 0.0] if abs(n[1]) < 0.9 else [1.0, 0.0, 0.0])
        t1 /= np.linalg.norm(t1)
        t2 = np.cross(n, t1)
        spacing = 0.5 * (np.linalg.norm(du) / max(min(u + 1, W - 1) - max(u - 1, 0), 1)
                         + np.linalg.norm(dv) / max(min(v + 1, H - 1) - max(v - 1, 0), 1))
        margin = int(math.ceil(MARGIN_THICKNESSES * self.thickness / spacing))
        step = max(spacing, GRID_STEP_M)  # the solve's grid: no finer than GRID_STEP_M
        rows, cols = np.flatnonzero(pressed.any(axis=1)), np.flatnonzero(pressed.any(axis=0))
        window = (slice(max(0, rows[0] - margin), min(H, rows[-1] + 1 + margin)),
                  slice(max(0, cols[0] - margin), min(W, cols[-1] + 1 + margin)))
        Pw = ref_depth[window] * rays[(slice(None),) + window]  # (3, h, w)
        rel = Pw - P(v, u)[:, None, None]
        x, y = np.einsum("k,khw->hw", t1, rel), np.einsum("k,khw->hw", t2, rel)
        cosine = -np.einsum("k,khw->hw", n, rays[(slice(None),) + window])  # ray (z = 1) along the normal
        delta_px = reach[window] * cosine  # the indenter's reach along the normal
        inside = pressed[window]
        # the grid: the window's extent in the plane, in steps of a pixel's size
        xs = np.arange(x.min(), x.max() + step, step)
        ys = np.arange(y.min(), y.max() + step, step)
        gx, gy = np.meshgrid(xs, ys, indexing="xy")  # (len(ys), len(xs))
        top = float(delta_px[inside].max())
        delta = griddata((x[inside], y[inside]), delta_px[inside], (gx, gy), method="linear", fill_value=np.nan)
        delta = np.where(np.isfinite(delta), delta, -top)
        contact = solve(delta, step, self.thickness, self.poisson)
        read = dict(bounds_error=False, fill_value=0.0)
        at = np.stack([y.ravel(), x.ravel()], axis=1)
        u_px = RegularGridInterpolator((ys, xs), contact.u, **read)(at).reshape(x.shape)
        pressure = RegularGridInterpolator((ys, xs), contact.pressure, **read)(at).reshape(x.shape)
        touching = RegularGridInterpolator((ys, xs), contact.contact.astype(float), method="nearest",
                                           **read)(at).reshape(x.shape) > 0.5
        mapped = Contact(u_px, pressure, touching & inside, contact.load_n, contact.volume_m3)
        return mapped, window, cosine, P(v, u), float(np.linalg.norm(rel, axis=0).max())

    def depth(self, depth: np.ndarray, ref_depth: np.ndarray) -> np.ndarray:
        """(H, W) the deformed membrane's depth, m: each pixel's D_ref less u over the
        cosine between its ray and the normal (the surface moved by u along the normal
        towards the camera; where u < 0, its bulge, away from it), on the indenter where
        it touches and never past it."""
        contact, window, cosine = self._found(depth, ref_depth)[:3]
        out = np.array(ref_depth, np.float64)
        if contact is not None:
            out[window] -= contact.u / cosine
            # the contact's conditions, as the solver holds them on its grid, held again on the
            # pixels (the resampling's rounding, a few um): on the indenter where it touches,
            # nowhere past it
            depth = np.asarray(depth, np.float64)
            pressed = depth < ref_depth
            out[pressed] = np.minimum(out[pressed], depth[pressed])
            touching = np.zeros_like(pressed)
            touching[window] = contact.contact
            out[touching] = depth[touching]
        return out


#: The depths, as shares of the ball's radius, at which ``ball_contact_radius`` is
#: tabulated for ``ball_depth_for_contact``, and the pixels across the ball's radius in
#: those solves (the contact's radius is its area's, good to a small share of a pixel).
DEPTH_SHARES = (0.02, 0.05, 0.1, 0.2, 0.3, 0.45, 0.6, 0.75, 0.9, 0.98)
BALL_PIXELS = 30


def ball_contact_radius(depth_m: float, ball_radius_m: float, thickness_m: float | None, poisson: float) -> float:
    """The contact's radius, m (its area's equivalent), of a rigid ball of
    ``ball_radius_m`` pressed ``depth_m`` into the layer (module doc; the ball's own
    sphere, not Hertz's paraboloid)."""
    if not 0 < depth_m < ball_radius_m:
        raise ValueError(f"a ball {ball_radius_m * 1e3:g} mm in radius is pressed between 0 and its radius, got "
                         f"{depth_m * 1e3:g} mm")
    pixel = ball_radius_m / BALL_PIXELS
    n = 2 * BALL_PIXELS + 2
    x = (np.arange(n) - n / 2 + 0.5) * pixel
    r = np.hypot(*np.meshgrid(x, x, indexing="ij"))
    cap = ball_radius_m - np.sqrt(np.clip(ball_radius_m**2 - r * r, 0.0, None))
    delta = np.where(r < ball_radius_m, depth_m - cap, -ball_radius_m)
    contact = solve(delta, pixel, thickness_m, poisson)
    return math.sqrt(contact.contact.sum() / math.pi) * pixel


def depth_at_radius(radius_m, radii_m, depths_m):
    """The depth at a contact's (or a rim's) radius from a tabulated relation (radii_m,
    depths_m), linear in the radius's square between its points (Hertz's depth is
    proportional to it) and held at its ends."""
    return np.interp(np.square(radius_m), np.square(radii_m), depths_m)


@functools.lru_cache(maxsize=8)
def _radii(ball_radius_m: float, thickness_m: float | None, poisson: float) -> tuple[np.ndarray, np.ndarray]:
    """(depths, contact radii) at DEPTH_SHARES of the ball's radius, solved once per ball and layer."""
    depths = np.array(DEPTH_SHARES) * ball_radius_m
    return depths, np.array([ball_contact_radius(d, ball_radius_m, thickness_m, poisson) for d in depths])


def ball_depth_for_contact(contact_radius_m: float, ball_radius_m: float, thickness_m: float | None,
                           poisson: float, cap: bool = False) -> float:
    """The depth, m, at which a rigid ball of ``ball_radius_m`` leaves an elastic contact
    ``contact_radius_m`` in radius on this layer: ``ball_contact_radius`` tabulated at
    DEPTH_SHARES of the ball's radius (once per ball and layer) and inverted, linearly in
    the contact's squared radius (Hertz's depth is proportional to it). ValueError for a
    contact outside the table (a press deeper than its last share of the ball's radius);
    with ``cap``, a contact wider than the table's widest is given its depth instead."""
    check_material(thickness_m, poisson)
    depths, radii = _radii(ball_radius_m, thickness_m, poisson)
    if np.any(np.diff(radii) <= 0):
        raise RuntimeError(f"the ball's contact radii did not grow with depth: {radii}")
    a = float(contact_radius_m)
    if cap and a > radii[-1]:
        return float(depths[-1])
    if not radii[0] <= a <= radii[-1]:
        raise ValueError(f"a contact {a * 1e3:.3g} mm in radius lies outside what a ball {ball_radius_m * 1e3:g} mm "
                         f"in radius leaves on this layer ({radii[0] * 1e3:.3g} to {radii[-1] * 1e3:.3g} mm, pressed "
                         f"{depths[0] * 1e3:.3g} to {depths[-1] * 1e3:.3g} mm)")
    return float(depth_at_radius(a, radii, depths))
