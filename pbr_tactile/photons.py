"""A two-pass estimator for light guided through the membrane: photons, then the camera.

Light reaches the coating mostly after many total internal reflections, so camera-side
path tracing (volpath) converges very slowly: its shadow rays cannot cross the
dielectric core. Here:

1. **Light pass** (``deposits``). Photons leave each LED sphere (uniform over its surface,
   cosine about the normal) carrying unit total flux, and are traced through the scene
   in one symbolic Dr.Jit loop: free flights and isotropic scattering in the elastomer
   (sigma_t, albedo), Fresnel reflection or refraction at the smooth dielectric
   interfaces (the core and the tube, with their IORs read from the scene's BSDFs), and
   the coating (``pbr_tactile.paint``), where each hit deposits its flux on the hit face's vertices with
   barycentric weights before reflecting back inside. A weight window set by a pilot
   pass (``weight_window``) splits photons heading for the dim tip and rouletted ones in
   the bright LED end, so every part of the coating gets about as many deposits.
2. **Density estimate** (``irradiance``). Per LED m, the irradiance per unit emitted
   flux e_m at each coating vertex is the deposited flux over the area within a kernel
   of stated radius (photon mapping's estimate: bias of order radius^2, consistent as
   the radius goes to 0).
3. **Camera pass** (``camera_pass``). Camera rays, jittered in strata of each pixel, are
   followed through the tube and the medium to the first coating hit, whose outgoing
   radiance is (rho / pi) sum_m e_m(x) Phi_m(lambda), Phi_m = pi A_m L_e,m the LED's
   spectral flux. The first dielectric hit (the tube's inner wall) follows both Fresnel
   branches.

The transport is wavelength independent (constant refractive indices, grey medium and
coating, as in ``pbr_tactile.scene``), so one scalar map and one scalar image per LED carry
every wavelength, and the film's response to each LED's spectrum is applied exactly
(``pbr_tactile.spectra.film_response``), with no wavelength sampling noise.

A glossy paint (``pbr_tactile.paint``: a diffuse base and a GGX flake lobe) is carried by
a second map. Photons reflect off the paint by either lobe (picked by its share), so the
maps hold the flux that arrives and the diffuse lobe's radiance is (1 - g) (rho / pi) e_m.
The camera is fixed, so each coating vertex is seen from one direction along the view path
through the tube (``camera_views``); every arrival also deposits its flux weighted by the
flake lobe's BRDF from its own direction towards that one (``GlossyView``), and the same
density estimate makes the lobe's radiance g l_m (photon mapping's radiance estimate, read
per vertex). Lanes that reach the paint another way (the tube's reflection, after
scattering) read the same map, so their view direction is the vertex's, not their own.
Beyond Monte Carlo noise, the approximations are
the kernel's blur and the piecewise-linear reconstruction on the coating mesh (edges of
``REFINED_EDGE_M``); the camera pass uses geometric normals at the interfaces.
"""

from __future__ import annotations

import functools
import hashlib
import math
import typing
from dataclasses import dataclass

import numpy as np

from .paint import Paint

#: Russian roulette starts after this many bounces of a photon.
RR_DEPTH = 8
#: Hard cap on photon bounces (trapped light needs tens).
PHOTON_MAX_DEPTH = 160
#: Hard cap on camera path vertices (tube, medium).
CAMERA_MAX_DEPTH = 24
#: Camera rays continue from their first scattering event in this many directions.
SCATTER_SPLIT = 16
#: Only camera rays still carrying more than this weight are split at a scattering event.
SPLIT_MIN_WEIGHT = 0.25
#: Generations of split photons traced at most (the last one splits no more).
MAX_GENERATIONS = 12
#: A photon heavier than its window splits into at most this many.
MAX_SPLIT = 8
#: Split photons restart this far inside the coating, along its inward normal, m.
SPAWN_OFFSET_M = 1e-7

#: The events a photon's path is tagged with by ``deposits(classes=True)``, one bit each:
#: transmitted through a glass surface (a dielectric interface: the elastomer's face on
#: the glass, the glass's face on the air), reflected at one (Fresnel or total internal
#: reflection), scattered in the elastomer, reflected by the paint. A deposit is
#: counted in the class of the events before it: class 0 is light straight from an LED.
PATH_EVENTS = ("glass", "interface_reflection", "scattered", "paint")
GLASS, REFLECTED, SCATTERED, PAINTED = (1 << k for k in range(len(PATH_EVENTS)))
#: The number of path classes, all combinations of PATH_EVENTS.
PATH_CLASSES = 1 << len(PATH_EVENTS)


def path_class_events(path_class: int) -> tuple[str, ...]:
    """The events (PATH_EVENTS) of a path class's bitmask; () for light straight from an LED."""
    if not 0 <= int(path_class) < PATH_CLASSES:
        raise ValueError(f"a path class must be in [0, {PATH_CLASSES}), got {path_class}")
    return tuple(e for k, e in enumerate(PATH_EVENTS) if int(path_class) >> k & 1)


@dataclass(frozen=True)
class Source:
    """A spherical Lambertian emitter: centre (3,) m, radius m, radiance spectrum
    (peak_nm, fwhm_nm, scale) and whether it sits in the elastomer (else in glass).

    With a ``cone_axis`` (unit (3,)) the source is directional instead: its photons leave
    the sphere's point on that axis, uniformly in solid angle within ``cone_half_angle_rad``
    of it (constant radiant intensity inside the cone, none outside), carrying the same
    total flux. Seen by the camera (directly, or in the glass' reflection) its sphere has
    the radiance that gives that intensity, I / (pi r^2) towards directions inside the cone
    and none outside (``seen_radiance``).
    """

    centre: tuple[float, float, float]
    radius: float
    peak_nm: float | None
    fwhm_nm: float | None
    scale: float
    in_elastomer: bool
    name: str
    cone_axis: tuple[float, float, float] | None = None
    cone_half_angle_rad: float = 0.0

    def __post_init__(self):
        if self.cone_axis is not None:
            axis = np.asarray(self.cone_axis, np.float64)
            if axis.shape != (3,) or not abs(float(np.linalg.norm(axis)) - 1.0) < 1e-6:
                raise ValueError(f"source {self.name}: cone_axis must be a unit 3-vector, got {self.cone_axis}")
            if not 0.0 < self.cone_half_angle_rad <= math.pi:
                raise ValueError(f"source {self.name}: cone_half_angle_rad must be in (0, pi], got "
                                 f"{self.cone_half_angle_rad}")

    @property
    def directional(self) -> bool:
        return self.cone_axis is not None

    def seen_radiance(self) -> float:
        """The radiance per unit flux of its sphere where the camera sees it: a Lambertian
        sphere's 1 / (pi A); a directional source's I / (pi r^2) = 1 / (Omega pi r^2) towards
        the cone's solid angle Omega, none outside it (``_camera_hit``)."""
        if not self.directional:
            return 1.0 / (math.pi * 4 * math.pi * self.radius**2)
        omega = 2 * math.pi * (1 - math.cos(self.cone_half_angle_rad))
        return 1.0 / (omega * math.pi * self.radius**2)

    def key(self) -> tuple:
        """What the light pass depends on, for cache keys."""
        base = (self.name, self.centre, self.radius, self.in_elastomer)
        return base if self.cone_axis is None else base + (tuple(self.cone_axis), self.cone_half_angle_rad)


def sources_from(leds: list[dict]) -> list[Source]:
    """Sources from ``pbr_tactile.scene.led_sources``."""
    return [Source(d["centre"], d["radius"], d["peak_nm"], d["fwhm_nm"], d["scale"], d["in_elastomer"], d["name"],
                   None if d.get("cone_axis") is None else tuple(map(float, d["cone_axis"])),
                   float(d.get("cone_half_angle_rad", 0.0)))
            for d in leds]


#: The per-lane cosine cutoff that marks a Lambertian start (cosine about the start normal).
_LAMBERTIAN = 2.0


def _start_direction(mi, dr, normal, cone_cos, u):
    """A photon's first direction: uniform in the cone of cosine cutoff ``cone_cos``
    about ``normal``, or cosine-weighted about it where ``cone_cos`` is _LAMBERTIAN."""
    frame = mi.Frame3f(normal)
    cone = mi.warp.square_to_uniform_cone(u, dr.minimum(cone_cos, 1.0))
    return frame.to_world(dr.select(cone_cos > 1.5, mi.warp.square_to_cosine_hemisphere(u), cone))


def _owned(cls, values):
    """A Dr.Jit array of type ``cls`` holding ``values`` (a NumPy array), copied to a
    64-byte-aligned buffer first. Dr.Jit's LLVM backend maps a NumPy buffer as it lies
    and specialises every kernel that reads it on whether its address is aligned to a
    vector (``jit_var_mem_map``), so arrays that NumPy happened to place differently
    compiled the same kernel anew: measured, every split generation of the photon pass
    missed the kernel cache, 0.2-0.4 s each, a third of a small render's time."""
    a = np.ascontiguousarray(values)
    buffer = np.empty(a.nbytes + 64, np.uint8)
    start = -buffer.ctypes.data % 64
    aligned = buffer[start:start + a.nbytes].view(a.dtype).reshape(a.shape)
    aligned[...] = a
    return cls(aligned)


def _pointer(mi, shape):
    """``shape`` as an opaque ShapePtr: a kernel parameter, not a literal. A literal
    pointer is the shape's index in Mitsuba's registry, which differs from one loaded
    scene to the next, and each new index compiled every kernel that compares against
    it anew (measured: 0.2-0.8 s a kernel, a few per render)."""
    import drjit as dr

    pointer = mi.ShapePtr(shape)
    dr.make_opaque(pointer)
    return pointer


def _splitmix(*parts: np.ndarray) -> np.ndarray:
    """A 64-bit hash (SplitMix64 steps) of integer arrays, element-wise."""
    with np.errstate(over="ignore"):
        h = np.zeros(np.broadcast(*parts).shape, dtype=np.uint64)
        for part in parts:
            h = (h ^ np.asarray(part).astype(np.uint64)) + np.uint64(0x9E3779B97F4A7C15)
            h = (h ^ (h >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
            h = (h ^ (h >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
            h = h ^ (h >> np.uint64(31))
    return h


def _seed(*parts: int) -> int:
    """One 32-bit sampler seed from several integers (pass, batch)."""
    return int(_splitmix(*(np.uint64(p % (1 << 64)) for p in parts)) & np.uint64(0xFFFFFFFF))


class _Rng:
    """Per-lane random streams keyed by a 64-bit identity, not by lane position.

    A photon (or camera ray) keeps its own stream whichever lane it lands in, so two
    renders with the same seed (a contact and the no-contact frame) trace the same
    walks wherever the geometry is the same: common random numbers, which keep the
    noise of a contact's change image down to the paths the contact actually changed.
    Offers the two sampler methods the walks use, and travels as Dr.Jit loop state.
    """

    DRJIT_STRUCT: typing.ClassVar[dict] = {"pcg": object}

    def __init__(self, mi=None, identity: np.ndarray | None = None):
        if mi is None:
            return
        import drjit as dr

        n = len(identity)
        # PCG32 adds arange(n) to both words; take it back so only the identity counts.
        offset = dr.arange(mi.UInt64, n)
        state = _owned(mi.UInt64, _splitmix(identity, np.uint64(1)))
        sequence = _owned(mi.UInt64, _splitmix(identity, np.uint64(2)))
        self.pcg = mi.PCG32(n, state - offset, sequence - offset)

    def next_1d(self, active=True):
        return self.pcg.next_float32(active)

    def next_2d(self, active=True):
        import mitsuba as mi

        return mi.Point2f(self.pcg.next_float32(active), self.pcg.next_float32(active))


def _shape(scene, name: str):
    for shape in scene.shapes():
        if shape.id() == name:
            return shape
    raise ValueError(f"the scene has no shape {name!r}")


@dataclass(frozen=True)
class _Coating:
    """The coating mesh as Dr.Jit buffers, and the shapes the walks tell apart."""

    faces: object  # UInt32 (3F,), vertex indices
    vertex_area: np.ndarray  # (V,) m^2, a third of each adjacent face's area
    coating: object  # ShapePtr
    core: object  # ShapePtr


def _coating(mi, scene) -> _Coating:
    import trimesh

    coating = _shape(scene, "coating")
    positions = np.asarray(coating.vertex_positions_buffer()).reshape(-1, 3)
    tri = np.asarray(coating.faces_buffer()).reshape(-1, 3)
    mesh = trimesh.Trimesh(positions, tri, process=False)
    vertex_area = np.zeros(len(positions))
    np.add.at(vertex_area, tri.ravel(), np.repeat(mesh.area_faces / 3, 3))
    return _Coating(_owned(mi.UInt32, tri.ravel()), vertex_area, _pointer(mi, coating), _pointer(mi, _shape(scene, "core")))


def _free_flight(dr, mi, sampler, ray, si, in_el, active, sigma_t: float):
    """Where a walk in the elastomer scatters before the next surface: (scatter, point)."""
    if sigma_t <= 0:
        return mi.Bool(False), ray.o
    t_free = -dr.log(1 - sampler.next_1d(active)) / sigma_t
    return active & in_el & (t_free < si.t), ray(t_free)


def _corners(mi, faces, pi, active):
    """The hit face's coating-vertex indices and the hit's barycentric weights, from a
    preliminary intersection (Mitsuba's p = (1-u-v) p0 + u p1 + v p2)."""
    import drjit as dr

    corners = tuple(dr.gather(mi.UInt32, faces, 3 * pi.prim_index + k, active) for k in range(3))
    return corners, (1 - pi.prim_uv.x - pi.prim_uv.y, pi.prim_uv.x, pi.prim_uv.y)


def _interfaces(mi, scene) -> list[tuple[object, float]]:
    """The smooth dielectric interfaces: (ShapePtr, eta = interior IOR / exterior IOR),
    by shape id: the scene lists its shapes in an order that varies from one load to the
    next, and each order made the kernels that test them differ (their etas are literals)."""
    out = []
    for shape in sorted(scene.shapes(), key=lambda s: s.id()):
        bsdf = shape.bsdf()
        if mi.has_flag(bsdf.flags(), mi.BSDFFlags.DeltaTransmission):
            out.append((_pointer(mi, shape), float(mi.traverse(bsdf)["eta"])))
    return out


def _dielectric(mi, dr, si, surface, interfaces):
    """Where the hit is a smooth dielectric interface, and its relative IOR there."""
    hit, eta = mi.Bool(False), mi.Float(1.0)
    for ptr, value in interfaces:
        here = surface & (si.shape == ptr)
        hit |= here
        eta = dr.select(here, value, eta)
    return hit, eta


def _fresnel_branches(mi, dr, d, n, eta):
    """Fresnel reflectance F, eta_ti and the refracted and reflected directions of d
    at a smooth interface of normal n (world space, geometric normal)."""
    wi = -d
    cos_i = dr.dot(wi, n)
    F, cos_t, _, eta_ti = mi.fresnel(cos_i, eta)
    refracted = dr.normalize(-eta_ti * (wi - n * cos_i) + n * cos_t)
    reflected = 2 * cos_i * n - wi
    return F, eta_ti, refracted, reflected


def _sample_dielectric(mi, dr, d, n, eta, u):
    """Fresnel-sampled reflection or refraction of direction d at a smooth interface of
    normal n: (new direction, transmitted, F, eta_ti).

    In importance transport the sampled weight is exactly 1 (the eta^2 factor applies
    to radiance only), as in Mitsuba's ``dielectric``.
    """
    F, eta_ti, refracted, reflected = _fresnel_branches(mi, dr, d, n, eta)
    transmitted = u >= F
    return dr.select(transmitted, refracted, reflected), transmitted, F, eta_ti


def _facing_shading_normal(mi, dr, si, towards):
    """The hit's shading normal (interpolated where the mesh has vertex normals), turned
    to the side of the unit direction ``towards`` (as ``twosided`` mirrors a BSDF)."""
    n = si.sh_frame.n
    return dr.select(dr.dot(n, towards) >= 0, n, -n)


def _paint_direction(mi, dr, paint, sampler, diffuse_dir, normal, wi, active):
    """A photon's direction off the paint and the weight factor beyond rho: the diffuse
    lobe (``diffuse_dir``, factor 1) or, with probability g, the flake lobe (factor G1)."""
    glossy_dir, factor = paint.sample_glossy(mi, dr, normal, wi, sampler.next_2d(active))
    pick = sampler.next_1d(active) < paint.gloss
    beyond = factor / paint.albedo if paint.albedo > 0 else 0.0
    return dr.select(pick, glossy_dir, diffuse_dir), dr.select(pick, beyond, 1.0)


class GlossyView:
    """Where the camera sees each coating vertex from, for a glossy paint's map
    (``deposits(glossy=)``): ``toward`` (V, 3) the unit direction from the vertex back along
    the camera's view path, ``normal`` (V, 3) its unit normal on the elastomer's side
    (``camera_views``). After ``deposits``, ``flux`` (S, V) is each vertex's share of
    sum_p Phi_p f(w_p, toward; normal) over the photons' arrivals p (the flake lobe's BRDF
    from the arrival's direction), which ``irradiance`` makes the lobe's radiance per unit
    flux emitted."""

    def __init__(self, toward: np.ndarray, normal: np.ndarray):
        self.toward = np.asarray(toward, np.float64)
        self.normal = np.asarray(normal, np.float64)
        if self.toward.shape != self.normal.shape or self.toward.ndim != 2 or self.toward.shape[1] != 3:
            raise ValueError(f"a glossy view needs (V, 3) directions and normals, got {self.toward.shape} and "
                             f"{self.normal.shape}")
        self.flux: np.ndarray | None = None


def _trace_generation(mi, scene, c: _Coating, interfaces, acc, target, start: dict, sampler, photons: int,
                      sigma_t: float, albedo: float, paint, may_split: bool, grid=None,
                      track=None, classes: int = 1, lobe=None) -> dict:
    """Trace one generation of photons from ``start``, depositing into ``acc`` (and, with a
    ``grid`` (``pbr_tactile.fluence.FluenceGrid``), their tracks in the elastomer into
    ``track``); returns the queue of photons the weight window split (slot per lane, k = 0
    where none). With ``classes`` = PATH_CLASSES, ``acc`` holds one block of vertices per
    source and path class, and each deposit goes to its path's class (PATH_EVENTS)."""
    import drjit as dr

    n_vertices = len(c.vertex_area)
    n_lanes = dr.width(start["s"])
    glossy = paint.glossy
    d = _start_direction(mi, dr, start["n"], start["cone"], sampler.next_2d())
    start_weight = start["w"]
    if glossy and "wi" in start:
        # Split photons restart on the paint: each copy draws its own lobe and direction.
        d, factor = _paint_direction(mi, dr, paint, sampler, d, start["shading"], start["wi"], True)
        start_weight = start_weight * factor
    ray = mi.Ray3f(start["p"], d)
    s, offset = start["s"], start["s"] * n_vertices
    keys = (("px", mi.Float), ("py", mi.Float), ("pz", mi.Float), ("nx", mi.Float), ("ny", mi.Float),
            ("nz", mi.Float), ("w", mi.Float), ("s", mi.UInt32), ("depth", mi.UInt32), ("k", mi.UInt32),
            ("id", mi.UInt64), ("tag", mi.UInt32))
    if glossy:  # where the photon came from and the shading normal, for the copies' lobes
        keys += tuple((k, mi.Float) for k in ("wx", "wy", "wz", "sx", "sy", "sz"))
    queue = {k: dr.zeros(t, n_lanes) for k, t in keys}
    lane_index = dr.arange(mi.UInt32, n_lanes)
    flags = mi.RayFlags.Minimal | mi.RayFlags.ShadingFrame if glossy else mi.RayFlags.Minimal

    def cond(ray, weight, in_el, active, depth, sampler, tag):
        return active

    def body(ray, weight, in_el, active, depth, sampler, tag):
        pi = scene.ray_intersect_preliminary(ray, False, active)
        si = pi.compute_surface_interaction(ray, flags, active)
        scatter, scatter_pos = _free_flight(dr, mi, sampler, ray, si, in_el, active, sigma_t)
        if grid is not None:
            # Track length: the segment's w l, at one point drawn uniformly along it.
            length = dr.select(scatter, dr.norm(scatter_pos - ray.o), si.t)
            crossed = active & in_el & (scatter | si.is_valid())
            at = ray(sampler.next_1d(active) * length)
            dr.scatter_reduce(dr.ReduceOp.Add, track, weight * length, s * grid.size + grid.index(mi, at), crossed,
                              mode=dr.ReduceMode.Expand)
        surface = active & ~scatter & si.is_valid()
        hit_coating = surface & (si.shape == c.coating)
        corners, bary = _corners(mi, c.faces, pi, hit_coating)
        into = offset if classes == 1 else (s * classes + tag) * n_vertices
        for i, b in zip(corners, bary):
            dr.scatter_reduce(dr.ReduceOp.Add, acc, weight * b, into + i, hit_coating,
                              mode=dr.ReduceMode.Expand)
        if lobe is not None:  # (acc, toward, normal): the lobe's BRDF from here towards each corner's view
            acc_g, toward, normal = lobe
            for i, b in zip(corners, bary):
                n_i = dr.gather(mi.Vector3f, normal, i, hit_coating)
                f_cos = paint.glossy_cos(mi, dr, n_i, dr.gather(mi.Vector3f, toward, i, hit_coating), -ray.d)
                cos_in = dr.dot(n_i, -ray.d)
                f = dr.select(cos_in > 1e-6, f_cos / dr.maximum(cos_in, 1e-6), 0.0)
                dr.scatter_reduce(dr.ReduceOp.Add, acc_g, weight * b * f, offset + i, hit_coating,
                                  mode=dr.ReduceMode.Expand)
        inward = -si.n
        diffuse_dir = mi.Frame3f(inward).to_world(mi.warp.square_to_cosine_hemisphere(sampler.next_2d(active)))
        if glossy:
            wi = -ray.d
            shading = _facing_shading_normal(mi, dr, si, wi)
            diffuse_dir, factor = _paint_direction(mi, dr, paint, sampler, diffuse_dir, shading, wi, hit_coating)
        dielectric, eta = _dielectric(mi, dr, si, surface, interfaces)
        refr_dir, transmitted, _, _ = _sample_dielectric(mi, dr, ray.d, si.n, eta, sampler.next_1d(active))
        in_el = dr.select(dielectric & transmitted & (si.shape == c.core), ~in_el, in_el)
        if classes > 1:
            tag = tag | dr.select(dielectric & transmitted, mi.UInt32(GLASS), mi.UInt32(0)) \
                | dr.select(dielectric & ~transmitted, mi.UInt32(REFLECTED), mi.UInt32(0)) \
                | dr.select(scatter, mi.UInt32(SCATTERED), mi.UInt32(0)) \
                | dr.select(hit_coating, mi.UInt32(PAINTED), mi.UInt32(0))
        scatter_dir = mi.warp.square_to_uniform_sphere(sampler.next_2d(active))
        weight = dr.select(hit_coating, weight * paint.albedo, weight)
        weight = dr.select(scatter, weight * albedo, weight)
        nxt = si.spawn_ray(dr.select(hit_coating, diffuse_dir, refr_dir))
        ray = mi.Ray3f(dr.select(scatter, scatter_pos, nxt.o), dr.select(scatter, scatter_dir, nxt.d))
        active = scatter | hit_coating | dielectric
        u = sampler.next_1d(active)
        if target is None:
            survive = dr.select(depth >= RR_DEPTH, dr.minimum(1.0, weight * photons), 1.0)
            alive = u < survive
            weight = dr.select(alive, weight / dr.maximum(survive, 1e-12), 0.0)
        else:
            nearest = dr.select(bary[0] >= dr.maximum(bary[1], bary[2]), corners[0],
                                dr.select(bary[1] >= bary[2], corners[1], corners[2]))
            goal = dr.gather(mi.Float, target, offset + nearest, hit_coating)
            light = hit_coating & (weight < 0.5 * goal)
            alive = ~light | (u * goal < weight)
            weight = dr.select(light & alive, goal, weight)
            if may_split:
                heavy = active & hit_coating & (weight > 2.0 * goal)
                k = mi.UInt32(dr.minimum(dr.round(weight / goal), MAX_SPLIT))
                # A lane splits at most once (it retires): its own slot in the queue.
                slot = lane_index
                stored = (("px", si.p.x), ("py", si.p.y), ("pz", si.p.z), ("nx", inward.x), ("ny", inward.y),
                          ("nz", inward.z), ("w", weight / mi.Float(k)), ("s", s), ("depth", depth + 1), ("k", k),
                          ("id", start["id"]), ("tag", tag))
                if glossy:
                    stored += (("wx", wi.x), ("wy", wi.y), ("wz", wi.z), ("sx", shading.x), ("sy", shading.y),
                               ("sz", shading.z))
                for key, value in stored:
                    dr.scatter(queue[key], value, slot, heavy)
                alive &= ~heavy
        if glossy:  # the lobe's factor beyond rho, after the window (the copies draw their own)
            weight = dr.select(hit_coating, weight * factor, weight)
            alive &= weight > 0
        depth += 1
        active &= alive & (depth < PHOTON_MAX_DEPTH)
        return ray, weight, in_el, active, depth, sampler, tag

    dr.while_loop(state=(ray, start_weight, start["in_el"], mi.Bool(True), start["depth"], sampler, start["tag"]),
                  cond=cond, body=body, labels=("ray", "weight", "in_el", "active", "depth", "sampler", "tag"),
                  label="photons")
    return queue


def deposits(mi, scene, sources: list[Source], sigma_t: float, albedo: float, coating_albedo: float,
             photons: int, seed: int = 0, window: np.ndarray | None = None, grid=None, classes: bool = False,
             glossy: GlossyView | None = None):
    """Per source, the flux each coating vertex receives, per unit flux emitted.

    All sources' photons are traced in one wavefront, as one symbolic Dr.Jit loop (one
    kernel: a photon's lane retires when its walk ends, with no per-bounce launches).
    A hit's flux is shared among its face's vertices with barycentric weights.
    ``coating_albedo`` is the paint's albedo, or a ``pbr_tactile.paint.Paint`` (a glossy
    one reflects photons by either lobe).

    window : optional (S, V) target photon weight at each coating vertex (a weight
        window, see ``weight_window``). After each coating deposit a photon lighter than
        half its target survives Russian roulette with probability weight / target and
        takes the target weight; one heavier than twice its target is split into
        k = min(round(weight / target), MAX_SPLIT) photons of weight / k, traced in the
        next generation. Both keep the estimate unbiased; they move photons from the
        bright LED end to the dim tip, so every part of the coating gets about the same
        number of deposits. Without a window, plain Russian roulette after RR_DEPTH.
    grid : a ``pbr_tactile.fluence.FluenceGrid``: the photons' tracks in the elastomer
        are summed per voxel too (``FluenceGrid.fluence`` makes them the fluence).
    classes : split each source's flux by the class of the path that brought it
        (PATH_EVENTS: the events before the deposit); the flux is then (S, PATH_CLASSES,
        V), its sum over the classes the flux without them. Tagging draws no random
        numbers, so a seed's walks are the same either way.
    glossy : a ``GlossyView`` (a glossy paint): its ``flux`` gets, per source and vertex,
        the arrivals' flux weighted by the flake lobe's BRDF towards the vertex's view. It
        draws no random numbers.
    Returns (S, V) float64, V the coating mesh's vertex count; with a grid, that and the
    (S, N) tracks, N the grid's voxels (m per unit flux emitted).
    """
    import drjit as dr

    paint = Paint.of(coating_albedo)
    c = _coating(mi, scene)
    n_vertices = len(c.vertex_area)
    n_src = len(sources)
    interfaces = _interfaces(mi, scene)
    n_classes = PATH_CLASSES if classes else 1
    acc = dr.zeros(mi.Float, n_src * n_classes * n_vertices)
    lobe = None
    if glossy is not None:
        if glossy.toward.shape != (n_vertices, 3):
            raise ValueError(f"the glossy view has {len(glossy.toward)} vertices, the coating {n_vertices}")
        lobe = (dr.zeros(mi.Float, n_src * n_vertices),
                *(mi.Vector3f(*[_owned(mi.Float, a[:, k]) for k in range(3)]) for a in (glossy.toward, glossy.normal)))
    track = None if grid is None else dr.zeros(mi.Float, n_src * grid.size)
    target = None if window is None else _owned(mi.Float, np.asarray(window, dtype=np.float64).ravel())

    # Generation 0: points on the LED spheres, cosine about their normals.
    lane = dr.arange(mi.UInt32, n_src * photons)
    s = lane // photons
    centre = dr.gather(mi.Point3f, mi.Point3f(*[mi.Float([src.centre[k] for src in sources]) for k in range(3)]), s)
    radius = dr.gather(mi.Float, mi.Float([src.radius for src in sources]), s)
    identity = _splitmix(np.uint64(seed), np.arange(n_src * photons, dtype=np.uint64))
    sampler = _Rng(mi, identity)
    normal = mi.warp.square_to_uniform_sphere(sampler.next_2d())
    # Directional sources leave from the sphere's point on their axis, within their cone.
    if any(src.directional for src in sources):
        axes = [src.cone_axis if src.directional else (0.0, 0.0, 1.0) for src in sources]
        axis = dr.gather(mi.Vector3f, mi.Vector3f(*[mi.Float([a[k] for a in axes]) for k in range(3)]), s)
        directional = dr.gather(mi.Bool, mi.Bool([src.directional for src in sources]), s)
        normal = dr.select(directional, axis, normal)
    cones = [math.cos(src.cone_half_angle_rad) if src.directional else _LAMBERTIAN for src in sources]
    start = {"p": centre + normal * (radius * (1 + 1e-4)), "n": normal, "w": mi.Float(1.0 / photons),
             "in_el": dr.gather(mi.Bool, mi.Bool([src.in_elastomer for src in sources]), s), "s": s,
             "depth": mi.UInt32(0), "id": _owned(mi.UInt64, identity), "cone": dr.gather(mi.Float, mi.Float(cones), s),
             "tag": dr.zeros(mi.UInt32, n_src * photons)}
    for generation in range(MAX_GENERATIONS):
        if generation > 0:
            sampler = _Rng(mi, identity)
        queue = _trace_generation(mi, scene, c, interfaces, acc, target, start, sampler, photons, sigma_t, albedo,
                                  paint, target is not None and generation < MAX_GENERATIONS - 1,
                                  grid, track, n_classes, lobe)
        logged = () if lobe is None else (lobe[0],)
        if target is None:
            break
        if track is None:
            dr.eval(acc, queue, *logged)
        else:
            dr.eval(acc, track, queue, *logged)
        split = np.asarray(queue["k"]) > 0
        if not split.any():
            break
        q = {key: np.asarray(value)[split] for key, value in queue.items()}
        copies = q["k"].astype(np.int64)
        rep = {key: np.repeat(value, copies) for key, value in q.items()}
        # Each copy's stream: its parent's identity, its copy number, the generation.
        copy = np.arange(len(rep["k"])) - np.repeat(np.cumsum(copies) - copies, copies)
        identity = _splitmix(rep["id"], copy.astype(np.uint64), np.uint64(generation + 1))
        p = np.c_[rep["px"], rep["py"], rep["pz"]]
        nrm = np.c_[rep["nx"], rep["ny"], rep["nz"]]
        p = p + nrm * SPAWN_OFFSET_M
        # Split photons restart on the coating, inside the elastomer.
        start = {"p": mi.Point3f(*[_owned(mi.Float, p[:, k]) for k in range(3)]),
                 "n": mi.Vector3f(*[_owned(mi.Float, nrm[:, k]) for k in range(3)]), "w": _owned(mi.Float, rep["w"]),
                 "in_el": dr.full(mi.Bool, True, len(rep["w"])), "s": _owned(mi.UInt32, rep["s"]),
                 "depth": _owned(mi.UInt32, rep["depth"]), "id": _owned(mi.UInt64, identity),
                 "cone": dr.full(mi.Float, _LAMBERTIAN, len(rep["w"])), "tag": _owned(mi.UInt32, rep["tag"])}
        if paint.glossy:
            start["wi"], start["shading"] = (mi.Vector3f(*[_owned(mi.Float, rep[k]) for k in names])
                                             for names in (("wx", "wy", "wz"), ("sx", "sy", "sz")))
    if lobe is not None:
        glossy.flux = np.asarray(lobe[0], dtype=np.float64).reshape(n_src, n_vertices)
    flux = np.asarray(acc, dtype=np.float64).reshape((n_src, n_classes, n_vertices) if classes else (n_src, n_vertices))
    return flux if track is None else (flux, np.asarray(track, dtype=np.float64).reshape(n_src, grid.size))


def weight_window(irradiance_pilot: np.ndarray, vertex_area: np.ndarray, photons: int,
                  deposits_per_photon: float = 2.5, exponent: float = 0.5) -> np.ndarray:
    """Target photon weights that move deposits from the bright LED end to the dim tip.

    A photon of weight w adds w to the flux at its hit, so the density of deposits is
    E(x) / w(x). The target w(x) = c E(x)^exponent gives a deposit density proportional
    to E^(1 - exponent): exponent 1 makes it uniform over the coating, 0 leaves it as
    unguided tracing has it (E). The default, 1/2, is the measured best: with exponent 1
    photons leave the bright end up to the whole irradiance contrast (~30x) heavier than
    the tip's target and deposit once at that weight before they split, and those
    spikes dominated the contact region's noise (RMS relative error 6.2 % against 4.0 %
    at 1/2, 4.5 % at 0, 4.2 % at 1/4, 4.9 % at 3/4, for the same time). c is set so the
    mean target is that of a uniform density of about ``deposits_per_photon`` deposits
    per photon traced. Any positive window keeps the estimate unbiased.

    irradiance_pilot : (S, V) a rough irradiance per unit flux (e.g. a few photons and a
        wide kernel); vertex_area (V,) m^2. Returns (S, V).
    """
    pilot = np.asarray(irradiance_pilot, dtype=np.float64)
    floor = 1e-3 * pilot.mean(axis=1, keepdims=True)  # vertices the pilot missed
    pilot = np.maximum(pilot, floor)
    mean = (pilot * vertex_area).sum(axis=1, keepdims=True) / vertex_area.sum()
    return pilot**exponent * mean ** (1 - exponent) * vertex_area.sum() / (deposits_per_photon * photons)


def coating_areas(scene) -> np.ndarray:
    """(V,) area attributed to each coating vertex, m^2 (a third of each adjacent face)."""
    import mitsuba as mi

    return _coating(mi, scene).vertex_area


def coating_vertices(scene) -> np.ndarray:
    """(V, 3) positions of the coating mesh's vertices, metres."""
    return np.asarray(_shape(scene, "coating").vertex_positions_buffer()).reshape(-1, 3)


def density_kernel(positions: np.ndarray, radius: float, like: tuple | None = None):
    """The (V, V) sparse Epanechnikov weights w_ij = 1 - (|x_i - x_j| / radius)^2 over a
    ball of the given radius (m); radius = 0 gives the identity.

    Vertices at the same position (a seam) weigh 1, like the diagonal. The last
    KERNEL_MEMO kernels are kept by the positions' bytes: every contact of a sensor
    asks again for the undeformed membrane's.

    like : (positions, kernel) of the same vertices before some of them moved (a contact's
        dent): only the moved vertices' rows and columns are computed again; the
        kernel is the one computed from scratch, entry for entry.
    """
    from scipy.sparse import csr_matrix, identity
    from scipy.spatial import cKDTree

    positions = np.ascontiguousarray(positions, dtype=np.float64)
    n = len(positions)
    if radius <= 0:
        return identity(n, format="csr")
    key = (hashlib.sha1(positions.tobytes()).hexdigest(), n, float(radius))
    if key in _KERNELS:
        _KERNELS[key] = _KERNELS.pop(key)  # the most recently used is kept longest
        return _KERNELS[key]

    def weights(i, j):
        return 1.0 - np.sum(np.square(positions[i] - positions[j]), axis=1) / radius**2

    if like is not None and len(like[0]) == n:
        old = like[1].tocoo()
        moved = np.any(positions != np.asarray(like[0], np.float64), axis=1)
        near = cKDTree(positions).query_ball_point(positions[moved], radius, return_sorted=False)
        rows = np.repeat(np.flatnonzero(moved), [len(k) for k in near])  # every pair with a moved vertex
        cols = np.concatenate(near).astype(np.int64) if len(near) else np.zeros(0, np.int64)
        w = weights(rows, cols)
        keep = ~moved[old.row] & ~moved[old.col]
        mirror = ~moved[cols]  # pairs of two moved vertices came from both their queries
        rows, cols, w = (np.concatenate([old.row[keep], rows, cols[mirror]]),
                         np.concatenate([old.col[keep], cols, rows[mirror]]),
                         np.concatenate([old.data[keep], w, w[mirror]]))
    else:
        pairs = cKDTree(positions).query_pairs(radius, output_type="ndarray")  # i < j
        w = weights(pairs[:, 0], pairs[:, 1])
        rows = np.concatenate([pairs[:, 0], pairs[:, 1], np.arange(n)])
        cols = np.concatenate([pairs[:, 1], pairs[:, 0], np.arange(n)])
        w = np.concatenate([w, w, np.ones(n)])
    kernel = csr_matrix((w, (rows, cols)), shape=(n, n))
    _KERNELS[key] = kernel
    while len(_KERNELS) > KERNEL_MEMO:
        _KERNELS.pop(next(iter(_KERNELS)))
    return kernel


#: Density kernels kept by ``density_kernel`` (each about 60 MB on the default GelTip mesh),
#: the most recently used.
KERNEL_MEMO = 2
_KERNELS: dict = {}


def irradiance(flux: np.ndarray, vertex_area: np.ndarray, kernel) -> np.ndarray:
    """Irradiance from deposited flux: E_i = sum_j w_ij Phi_j / sum_j w_ij A_j.

    That is the area-weighted mean irradiance over the kernel's ball around x_i: exact
    for irradiance linear over the ball, so its bias is of order radius^2 times the
    irradiance's curvature (photon mapping's density estimate, consistent as the radius
    goes to 0), while its variance falls as 1 / radius^2.

    flux : (S, V) deposited flux per vertex; vertex_area (V,) m^2; kernel from
    ``density_kernel``.
    """
    return (kernel @ flux.T).T / (kernel @ vertex_area)


#: Bump when the camera pass changes what a pixel sees (2: beam LEDs seen inside their
#: cone; 3: only on a ray's first segment): every cache of rendered images (bases, dataset frames, studies) keys on it.
CAMERA_PASS_VERSION = 3


#: The fewest rays ``camera_views`` traces over the film (a 640x480 grid's).
VIEW_RAYS = 640 * 480


def camera_views(mi, scene) -> GlossyView:
    """Where the scene's camera sees each coating vertex from, for a glossy paint's map.

    Rays on a grid over the film (at least VIEW_RAYS of them, so that every face in view
    is met whatever the film's size) are followed along their view paths, refracted at
    every interface (reflected only where it cannot cross), to the paint; each vertex takes
    the mean, weighted by the hits' barycentric weights, of the directions back along the
    rays that meet its faces (a vertex no ray meets: its normal). The normals are the
    mesh's own vertex normals (Mitsuba's, else trimesh's), turned to the elastomer's side.
    """
    import drjit as dr
    import trimesh

    c = _coating(mi, scene)
    coating = _shape(scene, "coating")
    interfaces = _interfaces(mi, scene)
    n_vertices = len(c.vertex_area)
    sensor = scene.sensors()[0]
    width, height = (int(v) for v in sensor.film().crop_size())
    per = max(1, math.ceil(math.sqrt(VIEW_RAYS / (width * height))))
    width, height = width * per, height * per
    index = dr.arange(mi.UInt32, width * height)
    position = (mi.Point2f(mi.Float(index % width), mi.Float(index // width)) + 0.5) / mi.ScalarVector2f(width, height)
    ray, _ = sensor.sample_ray(0.0, 0.5, position, mi.Point2f(0.5))
    acc = dr.zeros(mi.Float, 4 * n_vertices)  # per vertex: sum b w (3), sum b

    def cond(ray, active, depth):
        return active

    def body(ray, active, depth):
        pi = scene.ray_intersect_preliminary(ray, False, active)
        si = pi.compute_surface_interaction(ray, mi.RayFlags.Minimal, active)
        surface = active & si.is_valid()
        hit = surface & (si.shape == c.coating)
        corners, bary = _corners(mi, c.faces, pi, hit)
        for i, b in zip(corners, bary):
            for k, part in enumerate((-ray.d.x, -ray.d.y, -ray.d.z, mi.Float(1.0))):
                dr.scatter_reduce(dr.ReduceOp.Add, acc, b * part, 4 * i + k, hit, mode=dr.ReduceMode.Expand)
        dielectric, eta = _dielectric(mi, dr, si, surface, interfaces)
        F, _, refracted, reflected = _fresnel_branches(mi, dr, ray.d, si.n, eta)
        ray = si.spawn_ray(dr.select(F < 1, refracted, reflected))
        depth += 1
        return ray, dielectric & (depth < CAMERA_MAX_DEPTH), depth

    dr.while_loop(state=(mi.Ray3f(ray.o, ray.d), dr.full(mi.Bool, True, width * height),
                         dr.zeros(mi.UInt32, width * height)), cond=cond, body=body, label="camera_views")
    sums = np.asarray(acc, np.float64).reshape(n_vertices, 4)
    positions = np.asarray(coating.vertex_positions_buffer(), np.float64).reshape(-1, 3)
    if coating.has_vertex_normals():
        outward = np.asarray(coating.vertex_normals_buffer(), np.float64).reshape(-1, 3)
    else:
        faces = np.asarray(coating.faces_buffer()).reshape(-1, 3)
        outward = trimesh.Trimesh(positions, faces, process=False).vertex_normals
    normal = -outward / np.linalg.norm(outward, axis=1, keepdims=True)  # coating normals point out of the elastomer
    seen = sums[:, 3] > 0
    toward = normal.copy()
    toward[seen] = sums[seen, :3] / np.linalg.norm(sums[seen, :3], axis=1, keepdims=True)
    return GlossyView(toward, normal)


def camera_pass(mi, scene, sources: list[Source], maps: np.ndarray, sigma_t: float, albedo: float,
                coating_albedo: float, spp: int, seed: int = 0, batch: int = 1 << 21,
                scatter_split: int = SCATTER_SPLIT, fluence=None, glossy_maps: np.ndarray | None = None) -> np.ndarray:
    """Per pixel and source, the radiance reaching the camera per unit emitted flux.

    Camera rays (the scene's sensor, spp per pixel, one in each cell of a jittered grid
    over the pixel when spp is a square) are followed through the tube and the medium to
    the first coating hit, whose outgoing radiance is (rho / pi) e_m(x); LEDs seen
    directly give 1 / (pi A_m). At the first hit, the tube's inner wall, each ray
    follows both Fresnel branches with weights F and (1 - F) eta^2 instead of choosing
    one: the ~4 % reflection shows the bright LED end of the membrane and, sampled,
    would dominate every pixel's variance. Later interfaces are Fresnel-sampled.

    In the elastomer, absorption is a weight exp(-sigma_a t) along each segment, and
    scattering events are sampled at rate sigma_s; at a ray's first scattering event it
    continues in ``scatter_split`` directions, one in each stratum of the sphere, each
    with a 1/scatter_split share. In-scattered light is the whole camera-side noise
    (without the medium the contact region's noise is 0.36 % at 48 spp; with it, 2.5 %),
    so that is where the samples go.

    coating_albedo : the paint's albedo, or a ``pbr_tactile.paint.Paint``. A glossy paint's
        diffuse lobe is read from the maps, (1 - g) (rho / pi) e_m, and its flake lobe
        from ``glossy_maps``, g l_m.
    glossy_maps : (S, V) the flake lobe's radiance per unit flux towards each vertex's view
        (``GlossyView``'s flux through ``irradiance``), needed by a glossy paint.

    fluence : (grid, phi): a ``pbr_tactile.fluence.FluenceGrid`` and the (S, N) fluence
        per unit flux of each source in its voxels (``FluenceGrid.fluence`` of the photons'
        tracks). A ray's scattering event then ends its walk with the in-scattered
        radiance phi(x) / (4 pi) read there, which holds all the light that reaches x, the
        LEDs' through the glass included: no split, no next-event estimate
        (``pbr_tactile.fluence``; ``scatter_split`` is unused).

    The transport is grey, so no wavelength is sampled here: the film's response is
    applied exactly afterwards (pbr_tactile.spectra.film_response). Rays are traced in
    one symbolic loop per batch of at most ``batch`` camera samples.
    Returns (H, W, S) float64, 1/(m^2 sr) per unit flux.
    """
    import drjit as dr

    lookup = None
    if fluence is not None:
        grid, phi = fluence
        phi = np.asarray(phi)
        if phi.shape != (len(sources), grid.size):
            raise ValueError(f"fluence must be (sources, voxels) = ({len(sources)}, {grid.size}), got {phi.shape}")
        lookup = (grid, _owned(mi.Float, phi.ravel()))
        scatter_split = 1
    paint = Paint.of(coating_albedo)
    scale = 1.0 if paint.glossy else paint.albedo / math.pi
    if paint.glossy and glossy_maps is None:
        raise ValueError("a glossy paint's camera pass needs glossy_maps: the flake lobe's radiance per vertex, "
                         "from deposits(glossy=GlossyView(...))")
    c = _coating(mi, scene)
    interfaces = _interfaces(mi, scene)
    E = [_owned(mi.Float, m) for m in maps]
    if paint.glossy:
        glossy_maps = np.asarray(glossy_maps)
        if glossy_maps.shape != np.shape(maps):
            raise ValueError(f"glossy_maps must be shaped as the maps, {np.shape(maps)}, got {glossy_maps.shape}")
        # One map per source: (1 - g) (rho / pi) e_m + g l_m, read as the diffuse maps are.
        E = [_owned(mi.Float, (paint.diffuse / math.pi) * m + paint.gloss * l) for m, l in zip(maps, glossy_maps)]
    emitters = [_pointer(mi, _shape(scene, src.name)) for src in sources]
    # each source's radiance where seen, and the cone it shines into (Source.seen_radiance).
    # The axis is a scalar vector, copied into each expression: Dr.Jit 1.5 can broadcast a
    # literal Vector3f holding -0.0 (a turned LED's axis can) in place when it meets a wider
    # array, so one kept across the first hit and the walk broke the second.
    led_radiance = [(src.seen_radiance(), None if not src.directional else
                     (mi.ScalarVector3f(*src.cone_axis), math.cos(src.cone_half_angle_rad))) for src in sources]
    sensor = scene.sensors()[0]
    width, height = (int(v) for v in sensor.film().crop_size())
    side = math.isqrt(spp) if math.isqrt(spp) ** 2 == spp else 1
    total = np.zeros((width * height, len(sources)))
    per_batch = max(1, batch // (width * height))
    done = 0
    while done < spp:
        count = min(per_batch, spp - done)
        n = width * height * count
        sampler = mi.load_dict({"type": "independent"})
        sampler.seed(_seed(seed, 1 << 20, done), 2 * n)
        index = dr.arange(mi.UInt32, n)
        pixel = index // count
        sample = index % count + done
        px = mi.Point2f(mi.Float(pixel % width), mi.Float(pixel // width))
        cell = sample % (side * side)
        stratum = mi.Point2f(mi.Float(cell % side), mi.Float(cell // side))
        u = dr.gather(mi.Point2f, sampler.next_2d(), index)
        position = (px + (stratum + u) / side) / mi.ScalarVector2f(width, height)
        ray, _ = sensor.sample_ray(0.0, 0.5, position, mi.Point2f(0.5))
        ray = mi.Ray3f(ray.o, ray.d)
        # First hit: both Fresnel branches, as two lanes per camera sample.
        pi = scene.ray_intersect_preliminary(ray, False)
        si = pi.compute_surface_interaction(ray, mi.RayFlags.Minimal)
        T = _camera_hit(mi, dr, c, E, emitters, led_radiance, pi, si, si.is_valid(), mi.Float(1.0), scale,
                        direction=ray.d)
        dielectric, eta = _dielectric(mi, dr, si, si.is_valid(), interfaces)
        F, eta_ti, refracted, reflected = _fresnel_branches(mi, dr, ray.d, si.n, eta)
        enters = (si.shape == c.core)
        o_t, o_r = si.spawn_ray(refracted).o, si.spawn_ray(reflected).o
        # _concat gathers, which evaluates its sources: all in one kernel, not one each.
        dr.eval(T, dielectric, enters, F, eta_ti, refracted, reflected, o_t, o_r)

        def both(a, b):
            return _concat(mi, dr, a, b)

        lanes = mi.Ray3f(both(o_t, o_r), both(refracted, reflected))
        beta = both(dr.select(dielectric, (1 - F) * dr.square(eta_ti), 0.0), dr.select(dielectric, F, 0.0))
        in_el = both(dielectric & enters, dr.zeros(mi.Bool, n))
        walk = functools.partial(_camera_walk, mi, dr, scene, c, E, sources, emitters, led_radiance, interfaces,
                                 sigma_s=sigma_t * albedo, sigma_a=sigma_t * (1 - albedo),
                                 scale=scale, fluence=lookup)
        T2, scattered = walk(sampler, lanes, beta, in_el, stop_at_scatter=scatter_split > 1)
        # One kernel for every source's output (converting them one by one would trace
        # the walk once per source).
        dr.eval(T, T2, scattered)
        per_lane = np.stack([np.asarray(t, dtype=np.float64) for t in T2], axis=-1)  # (2n, S)
        if scatter_split > 1:
            nee = functools.partial(_led_nee, mi, dr, scene, sources, emitters, led_radiance, sigma_t=sigma_t)
            per_lane += _split_scatter(mi, dr, walk, nee, scattered, scatter_split, _seed(seed, 1 << 20, done), 2 * n)
        per_sample = np.stack([np.asarray(t, dtype=np.float64) for t in T], axis=-1) + per_lane.reshape(2, n, -1).sum(0)
        total += per_sample.reshape(width * height, count, -1).sum(axis=1)
        done += count
    return (total / spp).reshape(height, width, len(sources))


def _concat(mi, dr, a, b):
    """Two Dr.Jit arrays (or 3-vectors) of equal width, end to end."""
    if dr.depth_v(a) > 1:
        return type(a)(*[_concat(mi, dr, a[k], b[k]) for k in range(len(a))])
    n = dr.width(a)
    index = dr.arange(mi.UInt32, 2 * n)
    first = index < n
    return dr.select(first, dr.gather(type(a), a, index, first), dr.gather(type(a), b, index - n, ~first))


def _camera_hit(mi, dr, c, E, emitters, led_radiance, pi, si, surface, beta, scale, count_leds=True,
                direction=None, first=True):
    """Radiance per unit flux of each source, seen at a hit: the coating's map times
    ``scale`` (rho / pi times the irradiance e_m; a glossy paint's maps are already its
    radiance, scale 1) interpolated on the hit face, or an LED's radiance (``Source.seen_radiance``: ``led_radiance``
    holds it and, for a directional source, its cone's axis and cosine) where
    ``count_leds``, a directional one's only where ``direction`` (the ray's) leaves it
    inside its cone, and only on a ray's ``first`` segment past the camera's first hit
    (seen directly, or through or in the first interface): its sphere is small and bright,
    and its views after further sampled interfaces, rare, were most of every pixel's
    variance (bright single pixels all over the image), so they are left out."""
    hit_coating = surface & (si.shape == c.coating)
    corners, bary = _corners(mi, c.faces, pi, hit_coating)
    out = []
    for e, emitter, (radiance, cone) in zip(E, emitters, led_radiance):
        irr = sum(dr.gather(mi.Float, e, i, hit_coating) * b for i, b in zip(corners, bary))
        t = dr.select(hit_coating, beta * irr * scale, 0.0)
        lit = surface & count_leds & (si.shape == emitter)
        if cone is not None:
            lit = lit & first & (dr.dot(-direction, cone[0]) >= cone[1])
        out.append(t + dr.select(lit, beta * radiance, 0.0))
    return out


def _led_nee(mi, dr, scene, leds, emitters, led_radiance, point, beta, sampler, active, sigma_t: float):
    """Next-event estimate of each LED's light scattered towards the camera at points in
    the elastomer (isotropic phase 1/(4 pi)): a direction sampled uniformly in the cone
    the LED sphere subtends, kept if the sphere is the first thing it hits, attenuated by
    exp(-sigma_t t). Light reaching the point through an interface is not included (the
    walk itself finds it). Returns radiance per unit flux per source."""
    out = []
    for src, emitter, (radiance, cone) in zip(leds, emitters, led_radiance):
        to_led = mi.Point3f(*src.centre) - point
        dist = dr.norm(to_led)
        cos_max = dr.safe_sqrt(1 - dr.square(src.radius / dr.maximum(dist, src.radius * (1 + 1e-6))))
        d = mi.Frame3f(to_led / dist).to_world(mi.warp.square_to_uniform_cone(sampler.next_2d(active), cos_max))
        si = scene.ray_intersect(mi.Ray3f(point, d), mi.RayFlags.Minimal, False, active)
        seen = active & si.is_valid() & (si.shape == emitter)
        if cone is not None:  # a directional source lights only the points inside its cone
            seen = seen & (dr.dot(-d, cone[0]) >= cone[1])
        weight = beta * radiance / (4 * math.pi) * 2 * math.pi * (1 - cos_max) * dr.exp(-sigma_t * si.t)
        out.append(dr.select(seen, weight, 0.0))
    return out


def _camera_walk(mi, dr, scene, c, E, leds, emitters, led_radiance, interfaces, sampler, ray, beta, in_el,
                 sigma_s: float, sigma_a: float, scale: float, stop_at_scatter: bool = False,
                 after_scatter=None, fluence=None):
    """Follow camera rays (one symbolic loop) until they end on the coating, an LED or
    nothing. At a scattering event the LEDs' direct light comes by next-event estimation
    (``_led_nee``), so a segment starting there does not count an LED it hits (it would
    count that light twice); after an interface it does. Returns the radiance per unit
    flux of each source per lane, and, with ``stop_at_scatter``, the lanes stopped at
    their first scattering event (a dict of arrays: flag, position, weight, one slot per
    lane), else None. ``after_scatter``: lanes that start at a scattering event.
    ``fluence``: (FluenceGrid, its (S * N) Dr.Jit fluence): a scattering event adds
    beta phi(x) / (4 pi) and ends the lane (``camera_pass``)."""
    n_src = len(E)
    n = dr.width(beta)
    lane_index = dr.arange(mi.UInt32, n)
    stopped = {k: dr.zeros(mi.Float, n) for k in ("flag", "px", "py", "pz", "beta")} if stop_at_scatter else None
    sigma_t = sigma_s + sigma_a

    def cond(ray, beta, in_el, after, active, depth, sampler, *T):
        return active

    def body(ray, beta, in_el, after, active, depth, sampler, *T):
        pi = scene.ray_intersect_preliminary(ray, False, active)
        si = pi.compute_surface_interaction(ray, mi.RayFlags.Minimal, active)
        scatter, scatter_pos = _free_flight(dr, mi, sampler, ray, si, in_el, active, sigma_s)
        if sigma_a > 0:
            travelled = dr.select(scatter, dr.norm(scatter_pos - ray.o), si.t)
            beta = dr.select(active & in_el, beta * dr.exp(-sigma_a * dr.minimum(travelled, 1.0)), beta)
        surface = active & ~scatter & si.is_valid()
        seen = _camera_hit(mi, dr, c, E, emitters, led_radiance, pi, si, surface, beta, scale, ~after, ray.d,
                           depth == 0)
        T = [t + dt for t, dt in zip(T, seen)]
        dielectric, eta = _dielectric(mi, dr, si, surface, interfaces)
        wo, transmitted, _, eta_ti = _sample_dielectric(mi, dr, ray.d, si.n, eta, sampler.next_1d(active))
        in_el = dr.select(dielectric & transmitted & (si.shape == c.core), ~in_el, in_el)
        # Radiance crossing an interface is scaled by eta^2 (solid-angle compression).
        beta = dr.select(dielectric & transmitted, beta * dr.square(eta_ti), beta)
        scatter_dir = mi.warp.square_to_uniform_sphere(sampler.next_2d(active))
        nxt = si.spawn_ray(wo)
        ray = mi.Ray3f(dr.select(scatter, scatter_pos, nxt.o), dr.select(scatter, scatter_dir, nxt.d))
        depth += 1
        keep = scatter
        if fluence is not None:
            grid, phi = fluence
            voxel = grid.index(mi, scatter_pos)
            T = [t + dr.select(scatter, beta * dr.gather(mi.Float, phi, m * grid.size + voxel, scatter) / (4 * math.pi),
                               0.0) for m, t in enumerate(T)]
            keep = mi.Bool(False)
        elif stopped is not None:
            # Lanes carrying little (the tube's reflection, weight F) are not worth splitting.
            stop = scatter & (beta > SPLIT_MIN_WEIGHT)
            for key, value in (("flag", mi.Float(1.0)), ("px", scatter_pos.x), ("py", scatter_pos.y),
                               ("pz", scatter_pos.z), ("beta", beta)):
                dr.scatter(stopped[key], value, lane_index, stop)
            keep = scatter & ~stop
        if sigma_s > 0 and fluence is None:
            direct = _led_nee(mi, dr, scene, leds, emitters, led_radiance, scatter_pos, beta, sampler, keep, sigma_t)
            T = [t + dt for t, dt in zip(T, direct)]
        after = keep
        active = (keep | dielectric) & (beta > 0) & (depth < CAMERA_MAX_DEPTH)
        return (ray, beta, in_el, after, active, depth, sampler, *T)

    zeros = [dr.zeros(mi.Float, n) for _ in range(n_src)]
    after = dr.zeros(mi.Bool, n) if after_scatter is None else after_scatter
    state = dr.while_loop(state=(ray, beta, in_el, after, beta > 0, dr.zeros(mi.UInt32, n), sampler, *zeros),
                          cond=cond, body=body, label="camera")
    return list(state[7:]), stopped


def _split_scatter(mi, dr, walk, nee, stopped: dict, k: int, seed: int, n_lanes: int) -> np.ndarray:
    """Continue each stopped lane from its scattering point in k directions, one per
    stratum of the sphere (a jittered sqrt(k) x sqrt(k) grid on the unit square), each
    with weight beta / k. Returns (n_lanes, S) radiance per unit flux per lane."""
    flag = np.asarray(stopped["flag"]) > 0
    lanes = np.flatnonzero(flag)
    if len(lanes) == 0:
        return 0.0
    origin = np.c_[[np.asarray(stopped[key])[lanes] for key in ("px", "py", "pz")]].T
    beta = np.asarray(stopped["beta"])[lanes]
    side = max(1, math.isqrt(k))
    k = side * side
    m = len(lanes) * k
    # Streams keyed by the parent lane and the direction's stratum: a lane that scatters
    # in two renders (contact, no contact) continues the same way in both.
    sampler = _Rng(mi, _splitmix(np.uint64(seed), np.repeat(lanes, k).astype(np.uint64),
                                 np.tile(np.arange(k, dtype=np.uint64), len(lanes))))
    index = dr.arange(mi.UInt32, m)
    cell = index % k
    u = (mi.Point2f(mi.Float(cell % side), mi.Float(cell // side)) + sampler.next_2d()) / side
    d = mi.warp.square_to_uniform_sphere(u)
    o = np.repeat(origin, k, axis=0)
    ray = mi.Ray3f(mi.Point3f(*[_owned(mi.Float, o[:, j]) for j in range(3)]), d)
    weight = _owned(mi.Float, np.repeat(beta / k, k))
    T, _ = walk(sampler, ray, weight, dr.full(mi.Bool, True, m), after_scatter=dr.full(mi.Bool, True, m))
    # The LEDs' direct light at each event, one estimate per direction's stratum sample.
    direct = nee(ray.o, weight, sampler, dr.full(mi.Bool, True, m))
    T = [t + d for t, d in zip(T, direct)]
    dr.eval(T)
    per = np.stack([np.asarray(t, dtype=np.float64) for t in T], axis=-1).reshape(len(lanes), k, -1).sum(1)
    out = np.zeros((n_lanes, per.shape[1]))
    out[lanes] = per
    return out
