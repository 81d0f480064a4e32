"""A two-pass estimator for light guided through the membrane: photons, then the camera.

Light reaches the coating mostly after many total internal reflections, so camera-side
path tracing (volpath) converges very slowly: its shadow rays cannot cross the
dielectric core. Here:

1. **Light pass.** Photons leave each LED sphere (uniform over its surface, cosine about
   the normal) carrying unit total flux, and are traced through the scene: free flights
   and isotropic scattering in the elastomer (sigma_t, albedo), the dielectric core and
   tube sampled by Mitsuba's own BSDFs (importance transport, so flux is conserved), and
   the diffuse coating, where each hit deposits its flux on the hit face's vertices with
   barycentric weights before reflecting back inside. Per LED m, the deposits divided by
   each vertex's area give the irradiance per unit emitted flux, e_m (1/m^2).
2. **Camera pass.** A Mitsuba integrator follows camera rays through the tube and the
   medium (the same BSDFs, radiance transport) and stops at the first coating hit, where
   the coating's outgoing radiance is L = (rho / pi) sum_m e_m(x) Phi_m(lambda), with
   Phi_m = pi A_m L_e,m the LED's spectral flux. The film (``specfilm``) applies the
   camera's response exactly as for volpath.

The transport is taken as wavelength independent (constant refractive indices, grey
medium and coating, as in ``pbr_tactile.scene``), which lets one scalar map per LED carry
every wavelength. The coating must be diffuse (``coating_gloss = 0``). The only
approximation beyond Monte Carlo noise is the irradiance's piecewise-linear
reconstruction on the coating mesh (its edges are ``REFINED_EDGE_M``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Russian roulette starts after this many bounces of a photon.
RR_DEPTH = 8
#: Hard cap on photon bounces (trapped light needs tens).
PHOTON_MAX_DEPTH = 160
#: Hard cap on camera path vertices (tube, medium).
CAMERA_MAX_DEPTH = 24


@dataclass(frozen=True)
class Source:
    """A spherical Lambertian emitter: centre (3,) m, radius m, radiance spectrum
    (peak_nm, fwhm_nm, scale) and whether it sits in the elastomer (else in glass)."""

    centre: tuple[float, float, float]
    radius: float
    peak_nm: float | None
    fwhm_nm: float | None
    scale: float
    in_elastomer: bool


def sources_from(leds: list[dict]) -> list[Source]:
    """Sources from ``pbr_tactile.scene.led_sources``."""
    return [Source(d["centre"], d["radius"], d["peak_nm"], d["fwhm_nm"], d["scale"], d["in_elastomer"]) for d in leds]


def _shape(scene, name: str):
    for shape in scene.shapes():
        if shape.id() == name:
            return shape
    raise ValueError(f"the scene has no shape {name!r}")


@dataclass(frozen=True)
class _Coating:
    """The coating mesh as Dr.Jit buffers, and the shapes the walks tell apart."""

    faces: object  # UInt32 (3F,), vertex indices
    V: object  # Point3f (V,), vertex positions, metres
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
    return _Coating(mi.UInt32(tri.ravel()), mi.Point3f(*[mi.Float(positions[:, k]) for k in range(3)]), vertex_area,
                    mi.ShapePtr(coating), mi.ShapePtr(_shape(scene, "core")))


def _free_flight(dr, mi, sampler, ray, si, in_el, active, sigma_t: float):
    """Where a walk in the elastomer scatters before the next surface: (scatter, point)."""
    if sigma_t <= 0:
        return mi.Bool(False), ray.o
    t_free = -dr.log(1 - sampler.next_1d(active)) / sigma_t
    return active & in_el & (t_free < si.t), ray(t_free)


def _corners(mi, faces, V, si, active):
    """The hit face's vertex indices and the hit's barycentric weights (clamped)."""
    import drjit as dr

    f = si.prim_index
    i0, i1, i2 = (dr.gather(mi.UInt32, faces, 3 * f + k, active) for k in range(3))
    p0, p1, p2 = (dr.gather(mi.Point3f, V, i, active) for i in (i0, i1, i2))
    e1, e2, q = p1 - p0, p2 - p0, si.p - p0
    d11, d12, d22 = dr.dot(e1, e1), dr.dot(e1, e2), dr.dot(e2, e2)
    q1, q2 = dr.dot(q, e1), dr.dot(q, e2)
    den = d11 * d22 - d12 * d12
    b1 = dr.clip((d22 * q1 - d12 * q2) / den, 0, 1)
    b2 = dr.clip((d11 * q2 - d12 * q1) / den, 0, 1 - b1)
    return (i0, i1, i2), (1 - b1 - b2, b1, b2)


def irradiance_maps(mi, scene, sources: list[Source], sigma_t: float, albedo: float, coating_albedo: float,
                    photons: int, seed: int = 0) -> np.ndarray:
    """Per source, irradiance on the coating's vertices per unit emitted flux.

    Returns (S, V) float64, 1/m^2, V the coating mesh's vertex count.
    """
    import drjit as dr

    c = _coating(mi, scene)
    faces, V, coating_ptr, core_ptr = c.faces, c.V, c.coating, c.core
    n_vertices = len(c.vertex_area)
    ctx = mi.BSDFContext(mi.TransportMode.Importance)
    maps = []
    for s_index, src in enumerate(sources):
        acc = dr.zeros(mi.Float, n_vertices)
        sampler = mi.load_dict({"type": "independent"})
        sampler.seed(seed * 1009 + s_index, photons)
        n = mi.warp.square_to_uniform_sphere(sampler.next_2d())
        origin = mi.Point3f(*src.centre) + n * (src.radius * (1 + 1e-4))
        d = mi.Frame3f(n).to_world(mi.warp.square_to_cosine_hemisphere(sampler.next_2d()))
        ray = mi.Ray3f(origin, d)
        weight = mi.Float(1.0 / photons)
        in_el = mi.Bool(src.in_elastomer)
        active = mi.Bool(True)
        for depth in range(PHOTON_MAX_DEPTH):
            si = scene.ray_intersect(ray, active)
            scatter, scatter_pos = _free_flight(dr, mi, sampler, ray, si, in_el, active, sigma_t)
            surface = active & ~scatter & si.is_valid()
            hit_coating = surface & (si.shape == coating_ptr)
            # Deposit on the coating's vertices, barycentric weights.
            corners, weights = _corners(mi, faces, V, si, hit_coating)
            for i, b in zip(corners, weights):
                dr.scatter_reduce(dr.ReduceOp.Add, acc, weight * b, i, hit_coating)
            # Next direction.
            inward = -si.n
            diffuse_dir = mi.Frame3f(inward).to_world(mi.warp.square_to_cosine_hemisphere(sampler.next_2d()))
            dielectric = surface & ~hit_coating & has_transmission(mi, si)
            bs, bsdf_w = si.bsdf().sample(ctx, si, sampler.next_1d(dielectric), sampler.next_2d(dielectric), dielectric)
            refr_dir = si.to_world(bs.wo)
            transmitted = dielectric & mi.has_flag(bs.sampled_type, mi.BSDFFlags.Transmission)
            in_el = dr.select(transmitted & (si.shape == core_ptr), ~in_el, in_el)
            scatter_dir = mi.warp.square_to_uniform_sphere(sampler.next_2d())
            new_dir = dr.select(hit_coating, diffuse_dir, refr_dir)
            weight = dr.select(hit_coating, weight * coating_albedo, weight)
            weight = dr.select(dielectric, weight * bsdf_w[0], weight)
            weight = dr.select(scatter, weight * albedo, weight)
            next_ray = si.spawn_ray(new_dir)
            ray = mi.Ray3f(dr.select(scatter, scatter_pos, next_ray.o), dr.select(scatter, scatter_dir, next_ray.d))
            active = scatter | hit_coating | (dielectric & (bs.pdf > 0))
            if depth >= RR_DEPTH:
                survive = dr.minimum(1.0, weight * photons)
                alive = sampler.next_1d(active) < survive
                weight = dr.select(alive, weight / dr.maximum(survive, 1e-12), 0.0)
                active &= alive
            sampler.schedule_state()  # else the RNG state's graph grows every bounce
            dr.eval(acc, ray, weight, in_el, active)
            if not dr.any(active):
                break
        maps.append(np.asarray(acc, dtype=np.float64) / c.vertex_area)
    return np.stack(maps)


def has_transmission(mi, si):
    """Where the hit surface's BSDF can transmit (the dielectric interfaces)."""
    return mi.has_flag(si.bsdf().flags(), mi.BSDFFlags.Transmission)


def camera_integrator(mi, scene, sources: list[Source], maps: np.ndarray, sigma_t: float, albedo: float,
                      coating_albedo: float):
    """A Mitsuba integrator that looks up the photon irradiance at the first coating hit."""
    import drjit as dr

    c = _coating(mi, scene)
    faces, V, coating_ptr, core_ptr = c.faces, c.V, c.coating, c.core
    E = [mi.Float(m) for m in maps]

    def spectral_flux(src: Source, wavelengths):
        area = 4 * math.pi * src.radius**2
        if src.peak_nm is None:
            shape = mi.Spectrum(1.0)
        else:
            sigma = src.fwhm_nm / (2.0 * math.sqrt(2.0 * math.log(2.0)))
            shape = dr.exp(-0.5 * dr.square((wavelengths - src.peak_nm) / sigma))
        return shape * (math.pi * area * src.scale)

    class PhotonCamera(mi.SamplingIntegrator):
        def __init__(self, props=mi.Properties()):
            super().__init__(props)

        def sample(self, scene, sampler, ray, medium=None, active=True):
            ctx = mi.BSDFContext(mi.TransportMode.Radiance)
            ray = mi.Ray3f(ray)
            wavelengths = ray.wavelengths
            L = mi.Spectrum(0.0)
            beta = mi.Spectrum(1.0)
            in_el = mi.Bool(False)
            active = mi.Bool(active)
            for _ in range(CAMERA_MAX_DEPTH):
                si = scene.ray_intersect(ray, active)
                scatter, scatter_pos = _free_flight(dr, mi, sampler, ray, si, in_el, active, sigma_t)
                surface = active & ~scatter & si.is_valid()
                hit_coating = surface & (si.shape == coating_ptr)
                corners, weights = _corners(mi, faces, V, si, hit_coating)
                radiance = mi.Spectrum(0.0)
                for src, e in zip(sources, E):
                    irr = sum(dr.gather(mi.Float, e, i, hit_coating) * b for i, b in zip(corners, weights))
                    radiance += irr * spectral_flux(src, si.wavelengths)
                L += dr.select(hit_coating, beta * radiance * (coating_albedo / math.pi), 0.0)
                # LEDs seen directly (a null emitter evaluates to zero).
                L += beta * si.emitter(scene, surface).eval(si, surface)
                dielectric = surface & ~hit_coating & has_transmission(mi, si)
                bs, w = si.bsdf().sample(ctx, si, sampler.next_1d(dielectric), sampler.next_2d(dielectric), dielectric)
                transmitted = dielectric & mi.has_flag(bs.sampled_type, mi.BSDFFlags.Transmission)
                in_el = dr.select(transmitted & (si.shape == core_ptr), ~in_el, in_el)
                beta = dr.select(dielectric, beta * w, beta)
                beta = dr.select(scatter, beta * albedo, beta)
                scatter_dir = mi.warp.square_to_uniform_sphere(sampler.next_2d(scatter))
                nxt = si.spawn_ray(si.to_world(bs.wo))
                ray = mi.Ray3f(dr.select(scatter, scatter_pos, nxt.o), dr.select(scatter, scatter_dir, nxt.d),
                               ray.time, wavelengths)
                active = scatter | (dielectric & (bs.pdf > 0))
            return L, mi.Bool(True), []

    return PhotonCamera()
