"""The membrane's elastic response to a rigid contact, shared by both renderers.

Three models, by name (:data:`MODELS`):

- ``"published"``: the paper's image-space smoothing of the contact depth map,
  D_def = min(D, D_ref - G * (D_ref - D)) (:func:`deform`). Fast, and what the authors
  rendered; but it keeps the indenter's own shape inside its footprint and leaves
  near-vertical steps at sharp edges, and along grazing camera rays it is not a surface
  a membrane can take (the physically based reference cannot build a solid from it).
- ``"layer"``: the elastomer as a thin elastic layer bonded to the rigid glass core
  (a two-parameter, Pasternak-Vlasov foundation). Each point of the outer surface moves
  along its inward normal by w >= 0, the displacement minimising

      E(w) = 1/2 integral of (|grad w|^2 + w^2 / l^2) dA,   subject to  w >= delta,

  where delta is how far the rigid indenter reaches past the undeformed surface along
  the normal (:func:`penetration`). Where the indenter touches, the membrane conforms to
  it (w = delta); around it, w decays over the length l. Vlasov's layer of thickness h
  with a linear decay through its depth gives l = h sqrt((1 - nu) / 6) (0.72 mm for the
  GelTip's 2.5 mm of silicone, nu = 0.5). The displacement is capped at the thickness
  less MIN_GAP_M, so the surface never enters the glass core, and on a convex membrane
  whose curvature radius exceeds the thickness it cannot fold: moving inward along the
  normal only shrinks the tangent plane by (1 - w kappa) > 0.

- ``"bonded"``: the elastomer as an elastic solid of its thickness and Poisson's ratio
  bonded to its support (``scenes.elastic_solid``), on a flat membrane seen head-on;
  there the surface sinks outside the contact as a solid's does and an incompressible
  layer bulges round it. The fast path takes it; the reference does not yet.

``MembraneLayer`` holds the expensive per-membrane state (refined mesh, normals, the
stiffness matrix) and turns a contact depth map into the deformed surface
(``surface``) or, for the fast path, into the deformed surface's depth map
(``depth``), so both renderers see the same geometry for the same tap.
``layer_depth`` is the one-off function.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import trimesh
from scipy import ndimage, sparse, spatial
from scipy.sparse import linalg as sparse_linalg

from .camera import CONTACT_EPS_M, Camera, check_depth, project, reference_depth
from .proximity import interpolate
from .shapes import family
from .shapes.mesh import base_loop
from .spec import Elastic, SensorSpec

#: The elastic models, by name.
MODELS = ("published", "layer", "bonded")
#: Border handling of G; 'mirror' is OpenCV's default BORDER_REFLECT_101, which the
#: published implementation used.
BORDER_MODE = "mirror"
#: Target edge of the refined membrane the layer model works on, metres (a pixel spans
#: ~0.15 mm at the tip).
LAYER_EDGE_M = 0.25e-3
#: The deformed surface stays at least this far from the glass core, metres: the
#: elastomer does not compress below it (the indenter then rests on the glass through it).
MIN_GAP_M = 0.1e-3
#: A penetration deeper than the membrane's thickness by more than this is refused,
#: metres: the contact would pass through the glass core (scenes.protocol_checks.validate
#: refuses taps deeper than the thickness).
PENETRATION_TOLERANCE_M = 0.25e-3
#: The layer's displacement is solved within this many decay lengths of the contact;
#: beyond it w < exp(-8) of the indentation (under 1 um for a 2.5 mm one).
SUPPORT_LENGTHS = 8.0
#: Triangles of the contact surface seen this close to edge-on are depth-map
#: discontinuities (between an occluder and what it hides), not surface: |cos| below it.
EDGE_ON_COS = 0.05
#: Iterations of the primal-dual active-set solver (it converges in a few).
MAX_ACTIVE_SET_ITERATIONS = 50
#: Deformations a MembraneLayer keeps, the most recently solved: a contact rendered with
#: several light fields, or checked and then rendered, is solved once.
KEPT_DEFORMATIONS = 2


def smooth(delta: np.ndarray, elastic: Elastic) -> np.ndarray:
    """G * delta: the truncated Gaussian of the elastic model (55x55, sigma 5 px by default)."""
    return ndimage.gaussian_filter(
        delta, elastic.sigma_px, truncate=elastic.radius_px / elastic.sigma_px, mode=BORDER_MODE
    )


def deform(depth: np.ndarray, ref_depth: np.ndarray, elastic: Elastic) -> np.ndarray:
    """The published model: D_def = min(D, D_ref - G * (D_ref - D)).

    The rigid imprint D is spread by the Gaussian G as an elastic membrane would, and the
    min keeps the indenter's own surface where it reaches deeper than the spread.

    depth, ref_depth : (H, W) float, metres, planar z-depth.  Returns (H, W), same dtype.
    """
    return np.minimum(depth, ref_depth - smooth(ref_depth - depth, elastic))


def check_model(model: str, name: str = "elastic model") -> str:
    if model not in MODELS:
        raise ValueError(f"{name} must be one of {', '.join(MODELS)}, got {model!r}")
    return model


def layer_length(spec: SensorSpec, thickness=None):
    """The layer's decay length l = h sqrt((1 - nu) / 6), metres (Vlasov), for the
    elastomer's thickness h: ``thickness`` (a float or an array, metres), or the spec's
    stated one (``MembraneSpec.elastomer_thickness``)."""
    h = spec.membrane.elastomer_thickness if thickness is None else thickness
    if h is None:
        raise ValueError(f"sensor {spec.name!r} states no single thickness (its core is a mesh): pass the "
                         "thickness under each point (scenes.body.sensor_body(spec).thickness_at)")
    length = np.asarray(h, dtype=np.float64) * math.sqrt((1.0 - spec.elastic.poisson_ratio) / 6.0)
    return length if length.ndim else float(length)


def refine(mesh: trimesh.Trimesh, edge: float = LAYER_EDGE_M) -> trimesh.Trimesh:
    """Midpoint-subdivide every face until no edge exceeds ``edge`` (keeps it manifold)."""
    vertices, faces = trimesh.remesh.subdivide_to_size(mesh.vertices, mesh.faces, max_edge=edge)
    return trimesh.Trimesh(vertices, faces, process=True)


def contact_surface(depth: np.ndarray, ref_depth: np.ndarray, camera: Camera) -> trimesh.Trimesh | None:
    """The indenter's surface the camera sees inside the membrane, as a triangle mesh.

    The pixels where D < D_ref are back-projected and each 2x2 cell of them split in two
    triangles (one where only three corners are pressed), oriented towards the camera. Triangles seen edge-on (|cos| < EDGE_ON_COS)
    join an occluding part of the indenter to what it hides and are dropped. None when
    nothing is pressed.
    """
    pressed = depth < ref_depth - CONTACT_EPS_M
    if not pressed.any():
        return None
    rows, cols = np.nonzero(pressed)
    r0, r1 = max(rows.min() - 1, 0), min(rows.max() + 2, camera.height)
    c0, c1 = max(cols.min() - 1, 0), min(cols.max() + 2, camera.width)
    P = (depth[r0:r1, c0:c1, None] * camera.rays[r0:r1, c0:c1]).reshape(-1, 3)
    inside = pressed[r0:r1, c0:c1].ravel()
    h, w = r1 - r0, c1 - c0
    index = np.arange(h * w).reshape(h, w)
    a, b, c, d = index[:-1, :-1].ravel(), index[:-1, 1:].ravel(), index[1:, :-1].ravel(), index[1:, 1:].ravel()
    # A cell with all four corners pressed gives two triangles; one with three gives the
    # triangle of those three, so the surface ends within half a pixel of the contact's edge.
    full = inside[a] & inside[b] & inside[c] & inside[d]
    faces = np.concatenate([np.c_[a, c, b][full], np.c_[b, c, d][full]] + [
        tri[~full & inside[tri].all(axis=1)] for tri in (np.c_[a, c, b], np.c_[b, c, d], np.c_[a, c, d], np.c_[a, d, b])
    ])
    if len(faces) == 0:
        return None
    tri = P[faces]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(normal, axis=1)
    centre = tri.mean(axis=1)
    with np.errstate(divide="ignore", invalid="ignore"):
        cos = np.einsum("ij,ij->i", normal, centre) / (length * np.linalg.norm(centre, axis=1))
    keep = (length > 0) & (np.abs(cos) >= EDGE_ON_COS)
    faces, cos = faces[keep], cos[keep]
    faces[cos > 0] = faces[cos > 0][:, ::-1]  # normals towards the camera
    if len(faces) == 0:
        return None
    return trimesh.Trimesh(P, faces, process=False)


def penetration(
    vertices: np.ndarray, normals: np.ndarray, depth: np.ndarray, ref_depth: np.ndarray, camera: Camera,
    max_reach: float = np.inf,
) -> np.ndarray:
    """How far the rigid indenter of a contact depth map reaches past each surface point,
    along the point's inward normal.

    A ray from each point along -normal that leaves the indenter through its surface
    (:func:`contact_surface`, crossed from behind) started inside it: its length to that
    exit is the penetration. A ray that first meets the surface from the front, or
    nothing, started outside: 0.

    vertices, normals : (N, 3) float, metres and unit outward normals, camera frame.
    depth, ref_depth : (H, W) float, metres, the contact depth map D and D_ref.
    Returns (N,) float64 metres, >= 0.
    """
    out = np.zeros(len(vertices))
    surface = contact_surface(depth, ref_depth, camera)
    if surface is None:
        return out
    lo, hi = surface.bounds
    near = np.flatnonzero(((vertices >= lo - max_reach) & (vertices <= hi + max_reach)).all(axis=1))
    if len(near) == 0:
        return out
    start = 1e-6  # m, outside the surface point, so a contact surface through it is met
    origins = vertices[near] + start * normals[near]
    tri, ray, loc = surface.ray.intersects_id(origins, -normals[near], multiple_hits=False, return_locations=True)
    if len(ray) == 0:
        return out
    leaving = np.einsum("ij,ij->i", surface.face_normals[tri], -normals[near][ray]) > 0
    t = np.einsum("ij,ij->i", np.asarray(loc) - origins[ray], -normals[near][ray]) - start
    # An exit beyond ``reach`` is another part of the contact seen across the sensor.
    keep = leaving & (t <= max_reach)
    out[near[ray[keep]]] = np.maximum(t[keep], 0.0)
    return out


def solve_layer(K: sparse.csr_matrix, obstacle: np.ndarray) -> np.ndarray:
    """min 1/2 w^T K w subject to w >= obstacle, by primal-dual active sets.

    K : (n, n) sparse symmetric positive definite (stiffness; Dirichlet w = 0 beyond).
    obstacle : (n,) float, -inf where unconstrained.  Returns w (n,).
    """
    K = sparse.csr_matrix(K)
    active = obstacle > 0
    w = np.zeros(len(obstacle))
    for _ in range(MAX_ACTIVE_SET_ITERATIONS):
        w = np.where(active, obstacle, 0.0)
        free = np.flatnonzero(~active)
        if len(free) and active.any():
            rhs = -(K[free][:, np.flatnonzero(active)] @ obstacle[active])
            w[free] = sparse_linalg.spsolve(sparse.csc_matrix(K[free][:, free]), rhs)
        reaction = K @ w  # the contact pressure, >= 0 where the membrane touches
        scale = np.abs(reaction).max() or 1.0
        new = np.where(active, reaction > -1e-9 * scale, w < obstacle)
        if np.array_equal(new, active):
            break
        active = new
    return w


@dataclass(frozen=True)
class LayerDeformation:
    """The layer model's answer for one contact.

    vertices : (N, 3) float64, metres, the deformed outer surface (same faces).
    displacement : (N,) float64, metres, inward along the undeformed normal, w.
    penetration : (N,) float64, metres, the rigid indenter's reach past the surface, delta.
    """

    vertices: np.ndarray
    displacement: np.ndarray
    penetration: np.ndarray

    def __post_init__(self):
        for array in (self.vertices, self.displacement, self.penetration):
            array.flags.writeable = False  # a layer keeps its results: they are shared


class MembraneLayer:
    """The membrane as an elastic layer on the glass core (see module doc), precomputed.

    Parameters
    ----------
    mesh : the undeformed outer membrane surface, camera frame, metres; refined to
        ``edge`` (None: used as it is, e.g. already refined).
    spec : the sensor, for the layer's Poisson ratio and, by default, the thickness.
    camera : the camera the contact depth maps are taken with.
    thickness : the elastomer's thickness, metres: a float, or (V,) under each vertex of
        ``mesh``; None: the spec's stated thickness, or where it states none (its core is
        a mesh, or derived), its body's under each vertex (``scenes.body``).

    Attributes ``thickness`` and ``length`` hold (V,) values under each vertex of the
    refined mesh.
    """

    def __init__(self, mesh: trimesh.Trimesh, spec: SensorSpec, camera: Camera, edge: float | None = LAYER_EDGE_M,
                 thickness=None, bonded=None):
        self.bonded = bonded
        self.mesh = refine(mesh, edge) if edge is not None else mesh
        self.camera = camera
        self.vertices = np.asarray(self.mesh.vertices, dtype=np.float64)
        self.normals = np.asarray(self.mesh.vertex_normals, dtype=np.float64)
        tube = family(spec.membrane.shape).tube(spec.membrane)
        if thickness is None and tube is not None:
            thickness = tube.thickness
        if thickness is None:
            from .body import sensor_body

            thickness = sensor_body(spec).thickness_at(self.vertices)
        elif np.ndim(thickness) and self.mesh is not mesh:
            thickness = interpolate(mesh, np.asarray(thickness, dtype=np.float64), self.vertices)
        self.thickness = np.broadcast_to(np.asarray(thickness, dtype=np.float64), (len(self.vertices),)).copy()
        if self.thickness.shape != (len(self.vertices),) or not (self.thickness > MIN_GAP_M).all():
            raise ValueError(f"thickness must be > {MIN_GAP_M} m under every vertex, got {self.thickness.min()!r}")
        self.length = layer_length(spec, self.thickness)

    @cached_property
    def base(self) -> np.ndarray:
        """(K,) int, the refined mesh's boundary vertices (its open base), held fixed."""
        return base_loop(self.mesh, "the refined membrane")

    @cached_property
    def stiffness(self) -> sparse.csr_matrix:
        """K = L + M / l^2: the cotangent Laplacian and lumped vertex areas, so that
        E(w) = 1/2 w^T K w is the module doc's energy."""
        import potpourri3d as pp3d

        V, F = self.vertices, np.asarray(self.mesh.faces)
        L = pp3d.cotan_laplacian(V, F)
        M = pp3d.vertex_areas(V, F)
        return sparse.csr_matrix(L + sparse.diags(M / self.length**2))

    @cached_property
    def core_depth(self) -> tuple[np.ndarray, np.ndarray]:
        """Planar z-depth of the glass core's surface (H, W) float64, metres, and where the
        camera sees it (H, W) bool: a contact nearer than it is inside the glass."""
        core = trimesh.Trimesh(self.vertices - self.thickness[:, None] * self.normals, self.mesh.faces, process=False)
        depth, seen = reference_depth(core, self.camera)
        return depth.astype(np.float64), seen

    def deformation(self, depth: np.ndarray, ref_depth: np.ndarray) -> LayerDeformation:
        """The deformed surface for a contact depth map D (H, W) and D_ref, metres.

        Raises ValueError when the contact depth map reaches into the glass core by more
        than PENETRATION_TOLERANCE_M (deeper than the membrane). The last
        KEPT_DEFORMATIONS results are kept, keyed by the two maps' bytes.
        """
        from .cache import make_key

        depth = check_depth(depth, self.camera)
        ref_depth = check_depth(ref_depth, self.camera, "ref_depth")
        key = make_key(np.asarray(depth), np.asarray(ref_depth))
        kept = self.__dict__.setdefault("_kept", {})
        if key not in kept:
            kept[key] = self._deformation(depth, ref_depth)
            while len(kept) > KEPT_DEFORMATIONS:
                del kept[next(iter(kept))]
        return kept[key]

    def _deformation(self, depth: np.ndarray, ref_depth: np.ndarray) -> LayerDeformation:
        depth = depth.astype(np.float64)
        ref_depth = ref_depth.astype(np.float64)
        core, seen = self.core_depth
        inside = seen & (depth < core - PENETRATION_TOLERANCE_M)
        if inside.any():
            deepest = float((core - depth)[inside].max())
            raise ValueError(
                f"depth map pushes the indenter through the glass core at {int(inside.sum())} pixels (up to "
                f"{deepest * 1e3:.2f} mm past it along the camera ray, beyond a "
                f"{PENETRATION_TOLERANCE_M * 1e3:.2f} mm tolerance): deeper than the "
                f"{self.thickness.max() * 1e3:.2f} mm membrane"
            )
        delta = penetration(self.vertices, self.normals, depth, ref_depth, self.camera,
                            max_reach=float(self.thickness.max()) + PENETRATION_TOLERANCE_M)
        w = np.zeros(len(delta))
        touching = np.flatnonzero(delta > 0)
        if len(touching) and self.bonded is not None:
            w = self._bonded_displacement(depth, ref_depth, np.minimum(delta, self.thickness - MIN_GAP_M))
        elif len(touching):
            cap = self.thickness - MIN_GAP_M
            obstacle = np.minimum(delta, cap)
            # Solve near the contact only; beyond, w is below exp(-SUPPORT_LENGTHS).
            near, _ = spatial.cKDTree(self.vertices[touching]).query(
                self.vertices, distance_upper_bound=SUPPORT_LENGTHS * float(self.length.max()))
            # The base loop is held (w = 0 there): the elastomer solid is closed at it by the
            # undeformed base ring, which a pad's rim, near its contacts, would otherwise leave.
            near[self.base] = np.inf
            patch = np.flatnonzero(np.isfinite(near))
            K = self.stiffness[patch][:, patch]
            local = np.where(obstacle[patch] > 0, obstacle[patch], -np.inf)
            w[patch] = np.clip(solve_layer(K, local), 0.0, cap[patch])
        vertices = self.vertices - w[:, None] * self.normals
        return LayerDeformation(vertices, w, delta)

    def _bonded_displacement(self, depth: np.ndarray, ref_depth: np.ndarray, reach: np.ndarray) -> np.ndarray:
        """(V,) w of the ``bonded`` model (``scenes.elastic_solid.BondedLayer``): its
        displacement, solved on the contact's tangent plane from the depth maps, read at
        each vertex the camera places in its window and near the contact (bilinearly), then
        held between the indenter's ``reach`` (where it reaches a vertex) and the gap
        above the core. Its bulge (u < 0) is left out: a dent here only takes elastomer
        away (the reference's solids and fluence grids rely on it)."""
        contact, window, _, centre, near = self.bonded._found(depth, ref_depth)
        w = np.zeros(len(self.vertices))
        if contact is not None:
            rows, cols = window
            uv = project(self.vertices, self.camera)
            r, c = uv[:, 1] - rows.start, uv[:, 0] - cols.start
            h, wd = contact.u.shape
            seen = (r >= 0) & (r <= h - 1) & (c >= 0) & (c <= wd - 1) & (
                np.linalg.norm(self.vertices - centre, axis=1) <= near)
            w[seen] = ndimage.map_coordinates(contact.u, [r[seen], c[seen]], order=1, mode="nearest")
        return np.clip(np.maximum(w, reach), 0.0, self.thickness - MIN_GAP_M)

    def surface(self, depth: np.ndarray, ref_depth: np.ndarray) -> trimesh.Trimesh:
        """The deformed outer surface (the refined mesh's faces) for a contact."""
        return trimesh.Trimesh(self.deformation(depth, ref_depth).vertices, self.mesh.faces, process=False)

    def depth(self, depth: np.ndarray, ref_depth: np.ndarray) -> np.ndarray:
        """The deformed surface's planar z-depth map, as the fast path takes it.

        Where the layer did not move, D_ref; elsewhere the first hit of each pixel's ray
        with the deformed surface. (H, W) float, ``ref_depth``'s dtype.
        """
        result = self.deformation(depth, ref_depth)
        out = np.array(ref_depth, copy=True)
        moved = result.displacement > CONTACT_EPS_M
        if not moved.any():
            return out
        faces = np.asarray(self.mesh.faces)
        touched = moved[faces].any(axis=1)
        # Pixels that can see a moved face: their projections' box, one pixel wider.
        uv = project(np.vstack([result.vertices[faces[touched]].reshape(-1, 3),
                                self.vertices[faces[touched]].reshape(-1, 3)]), self.camera)
        c0, r0 = np.floor(uv.min(axis=0)).astype(int) - 1
        c1, r1 = np.ceil(uv.max(axis=0)).astype(int) + 2
        r0, c0 = max(r0, 0), max(c0, 0)
        r1, c1 = min(r1, self.camera.height), min(c1, self.camera.width)
        if r0 >= r1 or c0 >= c1:
            return out
        deformed = trimesh.Trimesh(result.vertices, faces, process=False)
        rays = self.camera.rays[r0:r1, c0:c1].reshape(-1, 3)
        dirs = rays / np.linalg.norm(rays, axis=1, keepdims=True)
        _, ray, loc = deformed.ray.intersects_id(np.zeros_like(dirs), dirs, multiple_hits=False,
                                                 return_locations=True)
        window = out[r0:r1, c0:c1].reshape(-1)
        z = np.einsum("ij,ij->i", np.asarray(loc), dirs[ray]) * dirs[ray, 2]
        # Embree works in float32: only a real change of depth replaces D_ref.
        window[ray] = np.where(z < window[ray] - CONTACT_EPS_M, z, window[ray])
        out[r0:r1, c0:c1] = window.reshape(r1 - r0, c1 - c0)
        return out


def layer_depth(
    depth: np.ndarray, ref_depth: np.ndarray, mesh: trimesh.Trimesh, spec: SensorSpec, camera: Camera
) -> np.ndarray:
    """One-off: the layer model's deformed depth map for a contact (see MembraneLayer)."""
    return MembraneLayer(mesh, spec, camera).depth(depth, ref_depth)
