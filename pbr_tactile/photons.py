"""The photon estimator's light pass: photons from the LEDs deposit their flux on the coating.

Light reaches the coating mostly after many total internal reflections, so camera-side
path tracing (volpath) converges very slowly: its shadow rays cannot cross the
dielectric core. The two-pass estimator (``pbr_tactile.render.render_photons`` runs it)
follows the light first:

1. **Light pass** (``deposits``, here). Photons leave each LED sphere (uniform over its surface,
   cosine about the normal) carrying unit total flux, and are traced through the scene
   in one symbolic Dr.Jit loop: free flights and isotropic scattering in the elastomer
   (sigma_t, albedo), Fresnel reflection or refraction at the smooth dielectric
   interfaces (the core and the tube, with their IORs read from the scene's BSDFs), and
   the coating (``pbr_tactile.paint``), where each hit deposits its flux on the hit face's vertices with
   barycentric weights before reflecting back inside. A weight window set by a pilot
   pass (``weight_window``) splits photons heading for the dim tip and rouletted ones in
   the bright LED end, so every part of the coating gets about as many deposits.
2. **Density estimate** (``pbr_tactile.density``): the irradiance per unit emitted flux
   e_m at each coating vertex, from the deposits.
3. **Camera pass** (``pbr_tactile.camera_pass``): camera rays to the coating, whose
   radiance the maps give.

What both passes' walks share (the interfaces' optics, free flights, the coating's
buffers) is in ``pbr_tactile.transport``, their random streams in ``pbr_tactile.streams``.

The transport is wavelength independent (constant refractive indices, grey medium and
coating, as in ``pbr_tactile.scene``), so one scalar map and one scalar image per LED carry
every wavelength, and the film's response to each LED's spectrum is applied exactly
(``pbr_tactile.spectra.film_response``), with no wavelength sampling noise.

A glossy paint (``pbr_tactile.paint``: a diffuse base and a GGX flake lobe) is carried by
a second map. Photons reflect off the paint by either lobe (picked by its share), so the
maps hold the flux that arrives and the diffuse lobe's radiance is (1 - g) (rho / pi) e_m.
The camera is fixed, so each coating vertex is seen from one direction along the view path
through the tube (``pbr_tactile.camera_pass.camera_views``); every arrival also deposits its
flux weighted by the flake lobe's BRDF from its own direction towards that one
(``GlossyView``), and the same density estimate makes the lobe's radiance g l_m (photon
mapping's radiance estimate, read per vertex). Lanes that reach the paint another way (the
tube's reflection, after scattering) read the same map, so their view direction is the
vertex's, not their own. Beyond Monte Carlo noise, the approximations are the kernel's blur
and the piecewise-linear reconstruction on the coating mesh (edges of ``REFINED_EDGE_M``);
the camera pass uses geometric normals at the interfaces.

The same walks also stand for other media and paints: ``deposits(perturb=)`` re-weights
every deposit and track to variants of (sigma_a, sigma_s, rho) by the path's length in the
elastomer, its scattering events and its paint bounces (perturbation Monte Carlo,
``pbr_tactile.reweight``), drawing no random numbers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .paint import Paint
from .reweight import Perturbation, Reweighted, path_factor
from .streams import Rng, splitmix
from .transport import (
    Coating,
    coating_buffers,
    dielectric_hit,
    dielectric_interfaces,
    face_corners,
    free_flight,
    owned,
    sample_dielectric,
)

#: Russian roulette starts after this many bounces of a photon.
RR_DEPTH = 8
#: Hard cap on photon bounces (trapped light needs tens).
PHOTON_MAX_DEPTH = 160
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
        the cone's solid angle Omega, none outside it
        (``pbr_tactile.camera_pass._camera_hit``)."""
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
    (``pbr_tactile.camera_pass.camera_views``). After ``deposits``, ``flux`` (S, V) is each
    vertex's share of sum_p Phi_p f(w_p, toward; normal) over the photons' arrivals p (the
    flake lobe's BRDF from the arrival's direction), which ``pbr_tactile.density.irradiance``
    makes the lobe's radiance per unit flux emitted."""

    def __init__(self, toward: np.ndarray, normal: np.ndarray):
        self.toward = np.asarray(toward, np.float64)
        self.normal = np.asarray(normal, np.float64)
        if self.toward.shape != self.normal.shape or self.toward.ndim != 2 or self.toward.shape[1] != 3:
            raise ValueError(f"a glossy view needs (V, 3) directions and normals, got {self.toward.shape} and "
                             f"{self.normal.shape}")
        self.flux: np.ndarray | None = None


def _trace_generation(mi, scene, c: Coating, interfaces, acc, target, start: dict, sampler, photons: int,
                      sigma_t: float, albedo: float, paint, may_split: bool, grid=None,
                      track=None, classes: int = 1, lobe=None, variants=None) -> dict:
    """Trace one generation of photons from ``start``, depositing into ``acc`` (and, with a
    ``grid`` (``pbr_tactile.fluence.FluenceGrid``), their tracks in the elastomer into
    ``track``); returns the queue of photons the weight window split (slot per lane, k = 0
    where none). With ``classes`` = PATH_CLASSES, ``acc`` holds one block of vertices per
    source and path class, and each deposit goes to its path's class (PATH_EVENTS).

    variants : (coefficients (K, 3), flux, track, moments, lobe): each deposit (and track,
        and with ``lobe`` its flake-lobe flux, into the last) is also added, times each
        variant's factor f (``pbr_tactile.reweight``, equation (1)), into ``flux`` (``track``) at K times ``acc``'s (``track``'s) index plus k (the
        variants of one vertex or voxel side by side, in one cache line: measured with 11
        variants at 2^15 photons, their added CPU time fell from about 1.0 to 0.6 of the
        pass's own against K blocks), and the deposits' moments into ``moments`` ((K + 1) S 2: the
        sums of w f and (w f)^2, the traced walk's first). The lanes then carry their path's
        elastomer length L, scattering events n and paint bounces m (``start``'s
        "length", "scatters", "bounces"), through the queue too."""
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
    if variants is not None:  # the path's statistics, for the copies' factors
        keys += (("length", mi.Float), ("scatters", mi.UInt32), ("bounces", mi.UInt32))
        coefficients, v_acc, v_track, moments, v_lobe = variants
        n_variants = len(coefficients)
    queue = {k: dr.zeros(t, n_lanes) for k, t in keys}
    lane_index = dr.arange(mi.UInt32, n_lanes)
    flags = mi.RayFlags.Minimal | mi.RayFlags.ShadingFrame if glossy else mi.RayFlags.Minimal

    def cond(ray, weight, in_el, active, depth, sampler, tag, *path):
        return active

    def body(ray, weight, in_el, active, depth, sampler, tag, *path):
        # path (with variants): L the elastomer length so far, m; n scattering events; m paint bounces.
        pi = scene.ray_intersect_preliminary(ray, False, active)
        si = pi.compute_surface_interaction(ray, flags, active)
        scatter, scatter_pos = free_flight(dr, mi, sampler, ray, si, in_el, active, sigma_t)
        if grid is not None or variants is not None:
            length = dr.select(scatter, dr.norm(scatter_pos - ray.o), si.t)
            crossed = active & in_el & (scatter | si.is_valid())
        if grid is not None:
            # Track length: the segment's w l, at one point drawn uniformly along it.
            u_track = sampler.next_1d(active)
            at = ray(u_track * length)
            voxel = s * grid.size + grid.index(mi, at)
            dr.scatter_reduce(dr.ReduceOp.Add, track, weight * length, voxel, crossed, mode=dr.ReduceMode.Expand)
            if variants is not None:  # each variant's factor at the scored point
                for k, coefficient in enumerate(coefficients):
                    f = path_factor(dr, coefficient, path[0] + u_track * length, path[1], path[2])
                    dr.scatter_reduce(dr.ReduceOp.Add, v_track, weight * length * f, voxel * n_variants + k,
                                      crossed, mode=dr.ReduceMode.Expand)
        surface = active & ~scatter & si.is_valid()
        hit_coating = surface & (si.shape == c.coating)
        corners, bary = face_corners(mi, c.faces, pi, hit_coating)
        into = offset if classes == 1 else (s * classes + tag) * n_vertices
        for i, b in zip(corners, bary):
            dr.scatter_reduce(dr.ReduceOp.Add, acc, weight * b, into + i, hit_coating,
                              mode=dr.ReduceMode.Expand)
        lobe_f = []  # per corner: the flake lobe's BRDF from here towards its view, over the cosine in
        if lobe is not None:  # (acc, toward, normal)
            acc_g, toward, normal = lobe
            for i, b in zip(corners, bary):
                n_i = dr.gather(mi.Vector3f, normal, i, hit_coating)
                f_cos = paint.glossy_cos(mi, dr, n_i, dr.gather(mi.Vector3f, toward, i, hit_coating), -ray.d)
                cos_in = dr.dot(n_i, -ray.d)
                f = dr.select(cos_in > 1e-6, f_cos / dr.maximum(cos_in, 1e-6), 0.0)
                lobe_f.append(f)
                dr.scatter_reduce(dr.ReduceOp.Add, acc_g, weight * b * f, offset + i, hit_coating,
                                  mode=dr.ReduceMode.Expand)
        if variants is not None:
            # The path up to this hit: the segment that ends here counts where it ran in the elastomer.
            L = path[0] + dr.select(crossed, length, 0.0)
            n_src_moments = dr.width(moments) // (2 * (len(coefficients) + 1))
            for k, coefficient in enumerate([None, *coefficients]):
                w_f = weight if coefficient is None else weight * path_factor(dr, coefficient, L, path[1], path[2])
                if coefficient is not None:
                    for i, b in zip(corners, bary):
                        dr.scatter_reduce(dr.ReduceOp.Add, v_acc, w_f * b, (into + i) * n_variants + k - 1,
                                          hit_coating, mode=dr.ReduceMode.Expand)
                    for i, b, f in zip(corners, bary, lobe_f):  # a glossy paint's lobe, re-weighted alike
                        dr.scatter_reduce(dr.ReduceOp.Add, v_lobe, w_f * b * f, (offset + i) * n_variants + k - 1,
                                          hit_coating, mode=dr.ReduceMode.Expand)
                at_k = (k * n_src_moments + s) * 2
                dr.scatter_reduce(dr.ReduceOp.Add, moments, w_f, at_k, hit_coating, mode=dr.ReduceMode.Expand)
                dr.scatter_reduce(dr.ReduceOp.Add, moments, w_f * w_f, at_k + 1, hit_coating,
                                  mode=dr.ReduceMode.Expand)
            path = (L, path[1] + dr.select(scatter, mi.UInt32(1), mi.UInt32(0)),
                    path[2] + dr.select(hit_coating, mi.UInt32(1), mi.UInt32(0)))
        inward = -si.n
        diffuse_dir = mi.Frame3f(inward).to_world(mi.warp.square_to_cosine_hemisphere(sampler.next_2d(active)))
        if glossy:
            wi = -ray.d
            shading = _facing_shading_normal(mi, dr, si, wi)
            diffuse_dir, factor = _paint_direction(mi, dr, paint, sampler, diffuse_dir, shading, wi, hit_coating)
        dielectric, eta = dielectric_hit(mi, dr, si, surface, interfaces)
        refr_dir, transmitted, _, _ = sample_dielectric(mi, dr, ray.d, si.n, eta, sampler.next_1d(active))
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
                if variants is not None:  # the copies restart after this bounce
                    stored += (("length", path[0]), ("scatters", path[1]), ("bounces", path[2]))
                for key, value in stored:
                    dr.scatter(queue[key], value, slot, heavy)
                alive &= ~heavy
        if glossy:  # the lobe's factor beyond rho, after the window (the copies draw their own)
            weight = dr.select(hit_coating, weight * factor, weight)
            alive &= weight > 0
        depth += 1
        active &= alive & (depth < PHOTON_MAX_DEPTH)
        return (ray, weight, in_el, active, depth, sampler, tag, *path)

    path = () if variants is None else (start["length"], start["scatters"], start["bounces"])
    dr.while_loop(state=(ray, start_weight, start["in_el"], mi.Bool(True), start["depth"], sampler, start["tag"],
                         *path),
                  cond=cond, body=body, labels=("ray", "weight", "in_el", "active", "depth", "sampler", "tag",
                                                *("L", "n", "m")[:len(path)]),
                  label="photons")
    return queue


def deposits(mi, scene, sources: list[Source], sigma_t: float, albedo: float, coating_albedo: float,
             photons: int, seed: int = 0, window: np.ndarray | None = None, grid=None, classes: bool = False,
             glossy: GlossyView | None = None, perturb=None, streams=None):
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
    perturb : a ``pbr_tactile.reweight.Perturbation`` or its (K, 3) array of variants
        (absorption_per_m, scattering_per_m, coating_albedo): every deposit (and track) is
        also re-weighted to each variant (``pbr_tactile.reweight``: equation (1), unbiased;
        it draws no random numbers, so the walks, and what is returned beside it, are
        those of the same seed without it). With a glossy paint (``glossy``), its flake
        lobe's flux is re-weighted alike (``Reweighted.lobe``); its albedo's variants are
        refused (``Perturbation.coefficients``).
    Returns (S, V) float64, V the coating mesh's vertex count; with a grid, that and the
    (S, N) tracks, N the grid's voxels (m per unit flux emitted). With ``perturb``, a pair:
    that, and the variants' ``pbr_tactile.reweight.Reweighted`` (flux (K, S, V), tracks
    (K, S, N) with a grid, the deposits' moments for the Kish ESS ratio (K, S)).
    """
    import drjit as dr

    paint = Paint.of(coating_albedo)
    variants = perturbation = None
    if perturb is not None:
        perturbation = Perturbation.of(perturb)
        coefficients = perturbation.coefficients(sigma_t, albedo, paint.albedo, paint.gloss)
    c = coating_buffers(mi, scene)
    n_vertices = len(c.vertex_area)
    n_src = len(sources)
    interfaces = dielectric_interfaces(mi, scene)
    n_classes = PATH_CLASSES if classes else 1
    acc = dr.zeros(mi.Float, n_src * n_classes * n_vertices)
    lobe = None
    if glossy is not None:
        if glossy.toward.shape != (n_vertices, 3):
            raise ValueError(f"the glossy view has {len(glossy.toward)} vertices, the coating {n_vertices}")
        lobe = (dr.zeros(mi.Float, n_src * n_vertices),
                *(mi.Vector3f(*[owned(mi.Float, a[:, k]) for k in range(3)]) for a in (glossy.toward, glossy.normal)))
    track = None if grid is None else dr.zeros(mi.Float, n_src * grid.size)
    target = None if window is None else owned(mi.Float, np.asarray(window, dtype=np.float64).ravel())
    if perturbation is not None:
        k = len(perturbation)
        variants = (coefficients, dr.zeros(mi.Float, k * dr.width(acc)),
                    None if track is None else dr.zeros(mi.Float, k * dr.width(track)),
                    dr.zeros(mi.Float, (k + 1) * n_src * 2),
                    None if lobe is None else dr.zeros(mi.Float, k * n_src * n_vertices))

    # Generation 0: points on the LED spheres, cosine about their normals.
    lane = dr.arange(mi.UInt32, n_src * photons)
    s = lane // photons
    centre = dr.gather(mi.Point3f, mi.Point3f(*[mi.Float([src.centre[k] for src in sources]) for k in range(3)]), s)
    radius = dr.gather(mi.Float, mi.Float([src.radius for src in sources]), s)
    streams = np.arange(n_src) if streams is None else np.asarray(streams, np.int64)
    if streams.shape != (n_src,) or (streams < 0).any() or len(set(streams.tolist())) != n_src:
        raise ValueError(f"streams must be {n_src} distinct non-negative source places, got {streams.tolist()}")
    identity = splitmix(np.uint64(seed), (np.repeat(streams, photons) * photons
                                          + np.tile(np.arange(photons), n_src)).astype(np.uint64))
    sampler = Rng(mi, identity)
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
             "depth": mi.UInt32(0), "id": owned(mi.UInt64, identity), "cone": dr.gather(mi.Float, mi.Float(cones), s),
             "tag": dr.zeros(mi.UInt32, n_src * photons)}
    if variants is not None:
        start.update(length=dr.zeros(mi.Float, n_src * photons), scatters=dr.zeros(mi.UInt32, n_src * photons),
                     bounces=dr.zeros(mi.UInt32, n_src * photons))
    for generation in range(MAX_GENERATIONS):
        if generation > 0:
            sampler = Rng(mi, identity)
        queue = _trace_generation(mi, scene, c, interfaces, acc, target, start, sampler, photons, sigma_t, albedo,
                                  paint, target is not None and generation < MAX_GENERATIONS - 1,
                                  grid, track, n_classes, lobe, variants)
        logged = (() if lobe is None else (lobe[0],)) + \
            (() if variants is None else tuple(a for a in variants[1:] if a is not None))
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
        identity = splitmix(rep["id"], copy.astype(np.uint64), np.uint64(generation + 1))
        p = np.c_[rep["px"], rep["py"], rep["pz"]]
        nrm = np.c_[rep["nx"], rep["ny"], rep["nz"]]
        p = p + nrm * SPAWN_OFFSET_M
        # Split photons restart on the coating, inside the elastomer.
        start = {"p": mi.Point3f(*[owned(mi.Float, p[:, k]) for k in range(3)]),
                 "n": mi.Vector3f(*[owned(mi.Float, nrm[:, k]) for k in range(3)]), "w": owned(mi.Float, rep["w"]),
                 "in_el": dr.full(mi.Bool, True, len(rep["w"])), "s": owned(mi.UInt32, rep["s"]),
                 "depth": owned(mi.UInt32, rep["depth"]), "id": owned(mi.UInt64, identity),
                 "cone": dr.full(mi.Float, _LAMBERTIAN, len(rep["w"])), "tag": owned(mi.UInt32, rep["tag"])}
        if paint.glossy:
            start["wi"], start["shading"] = (mi.Vector3f(*[owned(mi.Float, rep[k]) for k in names])
                                             for names in (("wx", "wy", "wz"), ("sx", "sy", "sz")))
        if variants is not None:
            start.update(length=owned(mi.Float, rep["length"]), scatters=owned(mi.UInt32, rep["scatters"]),
                         bounces=owned(mi.UInt32, rep["bounces"]))
    if lobe is not None:
        glossy.flux = np.asarray(lobe[0], dtype=np.float64).reshape(n_src, n_vertices)
    shape = (n_src, n_classes, n_vertices) if classes else (n_src, n_vertices)
    flux = np.asarray(acc, dtype=np.float64).reshape(shape)
    out = flux if track is None else (flux, np.asarray(track, dtype=np.float64).reshape(n_src, grid.size))
    if variants is None:
        return out
    k = len(perturbation)
    _, v_acc, v_track, moments, v_lobe = variants

    def variant_first(a, *dims):  # stored variant-minor (_trace_generation): variant first here
        return np.moveaxis(np.asarray(a, np.float64).reshape((*dims, k)), -1, 0).copy()

    return out, Reweighted(variant_first(v_acc, *shape),
                           None if v_track is None else variant_first(v_track, n_src, grid.size),
                           np.asarray(moments, np.float64).reshape(k + 1, n_src, 2),
                           None if v_lobe is None else variant_first(v_lobe, n_src, n_vertices))


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
