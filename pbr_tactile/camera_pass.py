"""The photon estimator's camera pass: camera rays to the coating, lit by the photon maps.

Camera rays, jittered in strata of each pixel, are followed through the tube and the
medium to the first coating hit, whose outgoing radiance is (rho / pi) sum_m e_m(x)
Phi_m(lambda), Phi_m = pi A_m L_e,m the LED's spectral flux, e_m the irradiance map of
``pbr_tactile.density`` (``camera_pass``). The first dielectric hit (the tube's inner
wall) follows both Fresnel branches. A glossy paint's flake lobe is read from a second
map, made towards where the camera sees each vertex from (``camera_views``; see
``pbr_tactile.photons``).
"""

from __future__ import annotations

import functools
import math

import numpy as np

from .paint import Paint
from .photons import GlossyView, Source
from .streams import Rng, sampler_seed, splitmix
from .transport import (
    coating_buffers,
    dielectric_hit,
    dielectric_interfaces,
    face_corners,
    fresnel_branches,
    free_flight,
    owned,
    sample_dielectric,
    shape_named,
    shape_pointer,
)

#: Hard cap on camera path vertices (tube, medium).
CAMERA_MAX_DEPTH = 24
#: Camera rays continue from their first scattering event in this many directions.
SCATTER_SPLIT = 16
#: Only camera rays still carrying more than this weight are split at a scattering event.
SPLIT_MIN_WEIGHT = 0.25


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

    c = coating_buffers(mi, scene)
    coating = shape_named(scene, "coating")
    interfaces = dielectric_interfaces(mi, scene)
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
        corners, bary = face_corners(mi, c.faces, pi, hit)
        for i, b in zip(corners, bary):
            for k, part in enumerate((-ray.d.x, -ray.d.y, -ray.d.z, mi.Float(1.0))):
                dr.scatter_reduce(dr.ReduceOp.Add, acc, b * part, 4 * i + k, hit, mode=dr.ReduceMode.Expand)
        dielectric, eta = dielectric_hit(mi, dr, si, surface, interfaces)
        F, _, refracted, reflected = fresnel_branches(mi, dr, ray.d, si.n, eta)
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
        lookup = (grid, owned(mi.Float, phi.ravel()))
        scatter_split = 1
    paint = Paint.of(coating_albedo)
    scale = 1.0 if paint.glossy else paint.albedo / math.pi
    if paint.glossy and glossy_maps is None:
        raise ValueError("a glossy paint's camera pass needs glossy_maps: the flake lobe's radiance per vertex, "
                         "from deposits(glossy=GlossyView(...))")
    c = coating_buffers(mi, scene)
    interfaces = dielectric_interfaces(mi, scene)
    E = [owned(mi.Float, m) for m in maps]
    if paint.glossy:
        glossy_maps = np.asarray(glossy_maps)
        if glossy_maps.shape != np.shape(maps):
            raise ValueError(f"glossy_maps must be shaped as the maps, {np.shape(maps)}, got {glossy_maps.shape}")
        # One map per source: (1 - g) (rho / pi) e_m + g l_m, read as the diffuse maps are.
        E = [owned(mi.Float, (paint.diffuse / math.pi) * m + paint.gloss * l) for m, l in zip(maps, glossy_maps)]
    emitters = [shape_pointer(mi, shape_named(scene, src.name)) for src in sources]
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
        sampler.seed(sampler_seed(seed, 1 << 20, done), 2 * n)
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
        dielectric, eta = dielectric_hit(mi, dr, si, si.is_valid(), interfaces)
        F, eta_ti, refracted, reflected = fresnel_branches(mi, dr, ray.d, si.n, eta)
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
            per_lane += _split_scatter(mi, dr, walk, nee, scattered, scatter_split, sampler_seed(seed, 1 << 20, done),
                                       2 * n)
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
    corners, bary = face_corners(mi, c.faces, pi, hit_coating)
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
        scatter, scatter_pos = free_flight(dr, mi, sampler, ray, si, in_el, active, sigma_s)
        if sigma_a > 0:
            travelled = dr.select(scatter, dr.norm(scatter_pos - ray.o), si.t)
            beta = dr.select(active & in_el, beta * dr.exp(-sigma_a * dr.minimum(travelled, 1.0)), beta)
        surface = active & ~scatter & si.is_valid()
        seen = _camera_hit(mi, dr, c, E, emitters, led_radiance, pi, si, surface, beta, scale, ~after, ray.d,
                           depth == 0)
        T = [t + dt for t, dt in zip(T, seen)]
        dielectric, eta = dielectric_hit(mi, dr, si, surface, interfaces)
        wo, transmitted, _, eta_ti = sample_dielectric(mi, dr, ray.d, si.n, eta, sampler.next_1d(active))
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
    sampler = Rng(mi, splitmix(np.uint64(seed), np.repeat(lanes, k).astype(np.uint64),
                                 np.tile(np.arange(k, dtype=np.uint64), len(lanes))))
    index = dr.arange(mi.UInt32, m)
    cell = index % k
    u = (mi.Point2f(mi.Float(cell % side), mi.Float(cell // side)) + sampler.next_2d()) / side
    d = mi.warp.square_to_uniform_sphere(u)
    o = np.repeat(origin, k, axis=0)
    ray = mi.Ray3f(mi.Point3f(*[owned(mi.Float, o[:, j]) for j in range(3)]), d)
    weight = owned(mi.Float, np.repeat(beta / k, k))
    T, _ = walk(sampler, ray, weight, dr.full(mi.Bool, True, m), after_scatter=dr.full(mi.Bool, True, m))
    # The LEDs' direct light at each event, one estimate per direction's stratum sample.
    direct = nee(ray.o, weight, sampler, dr.full(mi.Bool, True, m))
    T = [t + d for t, d in zip(T, direct)]
    dr.eval(T)
    per = np.stack([np.asarray(t, dtype=np.float64) for t in T], axis=-1).reshape(len(lanes), k, -1).sum(1)
    out = np.zeros((n_lanes, per.shape[1]))
    out[lanes] = per
    return out
