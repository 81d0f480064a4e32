"""What both passes' walks share: the scene's shapes as Dr.Jit data, and a hit's optics.

Both passes of the photon estimator (``pbr_tactile.photons``, ``pbr_tactile.camera_pass``)
follow their walks through the same scene in symbolic Dr.Jit loops: free flights in the
elastomer (``free_flight``); Fresnel reflection or refraction at the smooth dielectric
interfaces, the core and the tube, with their IORs read from the scene's BSDFs and
geometric normals (``dielectric_interfaces``, ``dielectric_hit``, ``fresnel_branches``,
``sample_dielectric``); and hits on the coating mesh, whose face's vertices and barycentric
weights index the photon maps (``coating_buffers``, ``face_corners``). NumPy arrays and
shapes enter the kernels so that each kernel compiles once (``owned``, ``shape_pointer``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def owned(cls, values):
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


def shape_pointer(mi, shape):
    """``shape`` as an opaque ShapePtr: a kernel parameter, not a literal. A literal
    pointer is the shape's index in Mitsuba's registry, which differs from one loaded
    scene to the next, and each new index compiled every kernel that compares against
    it anew (measured: 0.2-0.8 s a kernel, a few per render)."""
    import drjit as dr

    pointer = mi.ShapePtr(shape)
    dr.make_opaque(pointer)
    return pointer


def shape_named(scene, name: str):
    for shape in scene.shapes():
        if shape.id() == name:
            return shape
    raise ValueError(f"the scene has no shape {name!r}")


@dataclass(frozen=True)
class Coating:
    """The coating mesh as Dr.Jit buffers, and the shapes the walks tell apart."""

    faces: object  # UInt32 (3F,), vertex indices
    vertex_area: np.ndarray  # (V,) m^2, a third of each adjacent face's area
    coating: object  # ShapePtr
    core: object  # ShapePtr


def coating_buffers(mi, scene) -> Coating:
    import trimesh

    coating = shape_named(scene, "coating")
    positions = np.asarray(coating.vertex_positions_buffer()).reshape(-1, 3)
    tri = np.asarray(coating.faces_buffer()).reshape(-1, 3)
    mesh = trimesh.Trimesh(positions, tri, process=False)
    vertex_area = np.zeros(len(positions))
    np.add.at(vertex_area, tri.ravel(), np.repeat(mesh.area_faces / 3, 3))
    return Coating(owned(mi.UInt32, tri.ravel()), vertex_area, shape_pointer(mi, coating),
                   shape_pointer(mi, shape_named(scene, "core")))


def free_flight(dr, mi, sampler, ray, si, in_el, active, sigma_t: float):
    """Where a walk in the elastomer scatters before the next surface: (scatter, point)."""
    if sigma_t <= 0:
        return mi.Bool(False), ray.o
    t_free = -dr.log(1 - sampler.next_1d(active)) / sigma_t
    return active & in_el & (t_free < si.t), ray(t_free)


def face_corners(mi, faces, pi, active):
    """The hit face's coating-vertex indices and the hit's barycentric weights, from a
    preliminary intersection (Mitsuba's p = (1-u-v) p0 + u p1 + v p2)."""
    import drjit as dr

    corners = tuple(dr.gather(mi.UInt32, faces, 3 * pi.prim_index + k, active) for k in range(3))
    return corners, (1 - pi.prim_uv.x - pi.prim_uv.y, pi.prim_uv.x, pi.prim_uv.y)


def dielectric_interfaces(mi, scene) -> list[tuple[object, float]]:
    """The smooth dielectric interfaces: (ShapePtr, eta = interior IOR / exterior IOR),
    by shape id: the scene lists its shapes in an order that varies from one load to the
    next, and each order made the kernels that test them differ (their etas are literals)."""
    out = []
    for shape in sorted(scene.shapes(), key=lambda s: s.id()):
        bsdf = shape.bsdf()
        if mi.has_flag(bsdf.flags(), mi.BSDFFlags.DeltaTransmission):
            out.append((shape_pointer(mi, shape), float(mi.traverse(bsdf)["eta"])))
    return out


def dielectric_hit(mi, dr, si, surface, interfaces):
    """Where the hit is a smooth dielectric interface, and its relative IOR there."""
    hit, eta = mi.Bool(False), mi.Float(1.0)
    for ptr, value in interfaces:
        here = surface & (si.shape == ptr)
        hit |= here
        eta = dr.select(here, value, eta)
    return hit, eta


def fresnel_branches(mi, dr, d, n, eta):
    """Fresnel reflectance F, eta_ti and the refracted and reflected directions of d
    at a smooth interface of normal n (world space, geometric normal)."""
    wi = -d
    cos_i = dr.dot(wi, n)
    F, cos_t, _, eta_ti = mi.fresnel(cos_i, eta)
    refracted = dr.normalize(-eta_ti * (wi - n * cos_i) + n * cos_t)
    reflected = 2 * cos_i * n - wi
    return F, eta_ti, refracted, reflected


def sample_dielectric(mi, dr, d, n, eta, u):
    """Fresnel-sampled reflection or refraction of direction d at a smooth interface of
    normal n: (new direction, transmitted, F, eta_ti).

    In importance transport the sampled weight is exactly 1 (the eta^2 factor applies
    to radiance only), as in Mitsuba's ``dielectric``.
    """
    F, eta_ti, refracted, reflected = fresnel_branches(mi, dr, d, n, eta)
    transmitted = u >= F
    return dr.select(transmitted, refracted, reflected), transmitted, F, eta_ti
