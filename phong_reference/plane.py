"""Plane-section light field: light follows the membrane's cut by a plane through the LED.

The paper's plane method (Gomes, Paoletti, Luo, "Beyond Flat GelSight Sensors"): for LED m
at membrane vertex S with outward normal n_S, and a membrane point P, the plane through S
spanned by n_S and the chord S -> P cuts the membrane in a curve. Light reaches P along
that curve, so the field at P is the curve's unit tangent, oriented along the travel from
S to P.

The published code sliced the mesh once per pixel. Here:

* the tangent is analytic up to sign, ``t = N x n_pl / |N x n_pl|`` with
  ``n_pl = n_S x (P - S) / |n_S x (P - S)|`` and N the surface normal at P;
* only the sign needs the section's topology. All planes of one LED contain the line
  through S along n_S: a pencil with normals ``n_pl(psi) = cos(psi) e_1 + sin(psi) e_2``,
  psi in [0, pi). The pencil is sampled at N_PLANES angles and sliced all at once: each
  mesh edge crosses the planes of one analytic psi interval, and segments join the two
  crossed edges of each crossed face, so connectivity is exact;
* arc length from S along every section (one Dijkstra over all planes) orients each
  segment. P takes the orientation of the segments, in its own face (or a face around
  it), of the two sampled planes that bracket its plane. Where those two disagree (a
  section changes topology between them, or the meeting point of the two ways round a
  closed section passes P), P's exact plane is sliced and decides, as in the paper;
* P off S's component of its section, far from the sampled section, or with a sign that
  stays ambiguous is invalid, never guessed.

Closed sections (e.g. on a sphere) are travelled along the shorter way round; on an open
membrane such as the GelTip, light past the tip's apex travels back towards the base.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse
import scipy.sparse.csgraph
import trimesh

from scenes.camera import SurfaceSamples

from .sources import Sources

#: Bump when the method changes, so cached fields are rebuilt.
VERSION = 1

#: Sampled planes of each LED's pencil, spaced pi / N_PLANES in psi: a bracketing plane's
#: section passes within about |P - S| pi / N_PLANES of P (1.5e-4 m at 5 cm). Fewer planes
#: send more samples to the exact slice (256 planes take 5x longer on the GelTip).
N_PLANES = 1024

#: |n_S x (P - S)| / |P - S| and |N x n_pl| below this are degenerate (P on the pencil's
#: axis, or the plane tangent to the membrane at P): no section tangent.
MIN_SIN = 1e-6

#: |cos| between the sampled segment and t below this leaves the sign ambiguous.
MIN_SIGN_COS = 0.5

#: A segment whose arc length from S rises by less than this fraction of its length is
#: where two ways round a closed section meet: its orientation is ambiguous.
MIN_ARC_RISE = 0.5

#: P farther than this many mean edge lengths (plus the pencil spacing at P) from its
#: sampled segment is not on that section.
FAR_TOLERANCE_EDGES = 2.0

#: Slack on each edge's analytic psi interval; the exact vertex signs decide afterwards.
PSI_MARGIN_RAD = 1e-9


def pencil_frame(n_S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Orthonormal e_1, e_2 perpendicular to the pencil axis n_S (unit (3,))."""
    helper = np.eye(3)[np.argmin(np.abs(n_S))]
    e_1 = np.cross(n_S, helper)
    e_1 /= np.linalg.norm(e_1)
    return e_1, np.cross(n_S, e_1)


def section_tangents(
    points: np.ndarray, normals: np.ndarray, S: np.ndarray, n_S: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unsigned section tangents at membrane points.

    Parameters
    ----------
    points : (K, 3) float64, metres, the points P.
    normals : (K, 3) float64, unit surface normals N at P.
    S : (3,) float64, metres, the LED's membrane vertex.
    n_S : (3,) float64, unit surface normal at S.

    Returns
    -------
    t : (K, 3) float64, unit tangents N x n_pl of the section at P (sign arbitrary).
    n_pl : (K, 3) float64, unit normals n_S x (P - S) of the section planes.
    ok : (K,) bool, False where P is on the pencil axis or the plane is tangent at P.
    """
    chord = points - S
    n_pl = np.cross(n_S, chord)
    s = np.linalg.norm(n_pl, axis=1)
    ok = s > MIN_SIN * np.linalg.norm(chord, axis=1)
    n_pl = np.divide(n_pl, s[:, None], out=np.zeros_like(n_pl), where=ok[:, None])
    t = np.cross(normals, n_pl)
    s = np.linalg.norm(t, axis=1)
    ok &= s > MIN_SIN
    t = np.divide(t, s[:, None], out=np.zeros_like(t), where=ok[:, None])
    return t, n_pl, ok


def _ranges(start: np.ndarray, count: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Concatenated integer ranges [start_i, start_i + count_i): (owner i, value)."""
    owner = np.repeat(np.arange(len(count)), count)
    first = np.cumsum(count) - count
    return owner, start[owner] + np.arange(owner.size) - first[owner]


@dataclass(frozen=True)
class Sections:
    """Sections of a mesh by some planes of one LED's pencil, oriented by travel from S.

    psi : (J,) float64, radians, sorted plane angles; plane j has normal
        cos(psi_j) e_1 + sin(psi_j) e_2.
    key : (M,) int64, sorted, plane j * n_faces + face of each segment (one per crossed face).
    start, end : (M, 3) float64, metres, segment end points (on two edges of the face).
    travel : (M, 3) float64, metres, end - start or start - end: along increasing arc
        length from S.
    oriented : (M,) bool, the segment is on S's component and its orientation is decided.
    """

    psi: np.ndarray
    key: np.ndarray
    start: np.ndarray
    end: np.ndarray
    travel: np.ndarray
    oriented: np.ndarray


class PlaneBaker:
    """Plane-section fields on one membrane mesh (edge and face tables built once).

    Parameters
    ----------
    mesh : trimesh.Trimesh, metres; any triangle mesh, open or closed, convex or not.
    """

    def __init__(self, mesh: trimesh.Trimesh):
        self.mesh = mesh
        self.vertices = np.asarray(mesh.vertices, dtype=np.float64)  # (Nv, 3) m
        self.faces = np.asarray(mesh.faces, dtype=np.int64)  # (F, 3)
        self.edges = np.asarray(mesh.edges_unique, dtype=np.int64)  # (E, 2) vertex ids
        self.face_edges = np.asarray(mesh.faces_unique_edges, dtype=np.int64)  # (F, 3) edge ids
        # Edge -> faces, CSR: the faces of edge e are edge_faces[edge_ptr[e]:edge_ptr[e + 1]].
        flat = self.face_edges.ravel()
        self.edge_faces = np.argsort(flat, kind="stable") // 3
        self.edge_ptr = np.concatenate([[0], np.cumsum(np.bincount(flat, minlength=len(self.edges)))])
        lengths = np.linalg.norm(self.vertices[self.edges[:, 1]] - self.vertices[self.edges[:, 0]], axis=1)
        self.edge_length = float(lengths.mean())  # m
        # Faces sharing a vertex with each face, -1 padded: where a nearby plane's segment
        # lies when it misses P's own face.
        vf = np.asarray(mesh.vertex_faces)  # (Nv, max degree), -1 padded
        ring = np.sort(vf[self.faces].reshape(len(self.faces), -1), axis=1)
        ring[:, 1:][ring[:, 1:] == ring[:, :-1]] = -1
        self.face_ring = ring  # (F, R)

    # -- sections of a pencil ----------------------------------------------------------

    def sections(self, vertex: int, e_1: np.ndarray, e_2: np.ndarray, psi: np.ndarray) -> Sections:
        """Slice the mesh with planes of the pencil about S = vertices[vertex], oriented.

        Parameters
        ----------
        vertex : the LED's membrane vertex S.
        e_1, e_2 : (3,) unit, the pencil's frame (perpendicular to its axis n_S).
        psi : (J >= 1,) float, radians in [0, pi), sorted, unique: the planes.
        """
        V, edges, F = self.vertices, self.edges, len(self.faces)
        S = V[vertex]
        J = len(psi)
        xy = (V - S) @ np.stack([e_1, e_2], axis=1)  # (Nv, 2) m, in the pencil's frame
        rho = np.linalg.norm(xy, axis=1)
        # d_v(psi) = x_v cos(psi) + y_v sin(psi): an edge's end signs differ on an arc of psi
        # centred on its bisector + pi/2, as wide as the angle between the ends (mod pi).
        # Edges through the axis may cross every plane.
        ra, rb = rho[edges[:, 0]], rho[edges[:, 1]]
        tiny = 1e-12 * float(rho.max())
        ua = xy[edges[:, 0]] / np.maximum(ra, tiny)[:, None]
        ub = xy[edges[:, 1]] / np.maximum(rb, tiny)[:, None]
        alpha = np.arctan2(np.abs(ua[:, 0] * ub[:, 1] - ua[:, 1] * ub[:, 0]), (ua * ub).sum(axis=1))
        bis = ua + ub
        centre = np.mod(np.arctan2(bis[:, 1], bis[:, 0]) + np.pi / 2, np.pi)
        half = alpha / 2 + PSI_MARGIN_RAD
        wrapped = np.concatenate([psi - np.pi, psi, psi + np.pi])
        lo = np.searchsorted(wrapped, centre - half, side="left")
        count = np.searchsorted(wrapped, centre + half, side="right") - lo
        whole = (ra <= tiny) | (rb <= tiny) | (alpha > np.pi - 1e-6)
        lo[whole], count[whole] = 0, J
        edge, plane = _ranges(lo, count)
        plane %= J
        # Exact signs decide (d >= 0 counts as above, so S, on every plane, is on one side).
        c, s = np.cos(psi)[plane], np.sin(psi)[plane]
        i, k = edges[edge, 0], edges[edge, 1]
        d_i = xy[i, 0] * c + xy[i, 1] * s
        d_k = xy[k, 0] * c + xy[k, 1] * s
        cross = (d_i >= 0) != (d_k >= 0)
        edge, plane, i, k, d_i, d_k = edge[cross], plane[cross], i[cross], k[cross], d_i[cross], d_k[cross]
        position = V[i] + (d_i / (d_i - d_k))[:, None] * (V[k] - V[i])  # (Nn, 3) m, the nodes
        # Each crossed face holds exactly two crossed edges: their nodes make its segment.
        node, slot = _ranges(self.edge_ptr[edge], self.edge_ptr[edge + 1] - self.edge_ptr[edge])
        key = plane[node] * F + self.edge_faces[slot]
        order = np.argsort(key, kind="stable")
        key, node = key[order], node[order]
        pair = key[1:] == key[:-1]
        pair[1:] &= key[1:-1] != key[:-2]
        first = np.flatnonzero(pair)
        a, b, key = node[first], node[first + 1], key[first]

        # Arc length from S along each section: one Dijkstra over all planes, from one
        # virtual source per plane joined to the nodes on S's faces.
        n = len(position)
        eps = 1e-9 * self.edge_length  # csgraph drops zero weights; keep zero-length links
        star = np.zeros(len(edges), bool)
        star[self.face_edges[(self.faces == vertex).any(axis=1)].ravel()] = True
        near = np.flatnonzero(star[edge])
        source_planes, source = np.unique(plane[near], return_inverse=True)
        graph = scipy.sparse.csr_matrix(
            (
                np.concatenate(
                    [np.linalg.norm(position[a] - position[b], axis=1), np.linalg.norm(position[near] - S, axis=1)]
                )
                + eps,
                (np.concatenate([a, n + source]), np.concatenate([b, near])),
            ),
            shape=(n + len(source_planes),) * 2,
        )
        arc = scipy.sparse.csgraph.dijkstra(
            graph, directed=False, indices=n + np.arange(len(source_planes)), min_only=True
        )[:n]

        # Orient each segment along increasing arc length; undecided off S's component and
        # where the two ways round a closed section meet.
        start, end = position[a], position[b]
        length = np.linalg.norm(end - start, axis=1)
        reached = np.isfinite(arc[a]) & np.isfinite(arc[b])
        rise = np.where(reached, arc[b] - np.where(reached, arc[a], 0.0), 0.0)
        travel = (end - start) * np.sign(rise)[:, None]
        oriented = reached & (np.abs(rise) >= MIN_ARC_RISE * length) & (length > eps)
        return Sections(psi, key, start, end, travel, oriented)

    def travel_signs(
        self,
        sections: Sections,
        plane: np.ndarray,
        points: np.ndarray,
        faces: np.ndarray,
        t: np.ndarray,
        reach: np.ndarray,
    ) -> np.ndarray:
        """Sign that orients each tangent t along the travel, from one section per point.

        Parameters
        ----------
        sections : the sliced planes.
        plane : (K,) int, index into sections.psi of the plane used for each point.
        points : (K, 3) float64, metres, membrane points P.
        faces : (K,) int, the face holding each P.
        t : (K, 3) float64, unit tangents at P.
        reach : (K,) float64, metres, farthest the plane's segment may lie from P.

        Returns
        -------
        (K,) float64: +1 or -1, or 0 where undecided. The segment used is the plane's in
        P's face, else the nearest one in the faces around it.
        """
        P = points
        K, F = len(P), len(self.faces)
        if len(sections.key) == 0:
            return np.zeros(K)
        seg = np.zeros(K, np.int64)
        gap = np.full(K, np.inf)  # m, distance from P to its segment
        todo = np.arange(K)
        for cand in (faces[:, None], self.face_ring[faces]):
            if len(todo) == 0:
                break
            cand = cand[todo]
            key = plane[todo, None] * F + cand
            pos = np.minimum(np.searchsorted(sections.key, key), len(sections.key) - 1)
            hit = (cand >= 0) & (sections.key[pos] == key)
            a = sections.start[pos]
            ab = sections.end[pos] - a
            ap = P[todo, None] - a
            ab2 = (ab * ab).sum(-1)
            hit &= ab2 > 0
            lam = np.clip((ap * ab).sum(-1) / np.where(hit, ab2, 1.0), 0.0, 1.0)
            dist = np.where(hit, np.linalg.norm(ap - lam[..., None] * ab, axis=-1), np.inf)
            best = np.argmin(dist, axis=1)
            rows = np.arange(len(todo))
            seg[todo] = pos[rows, best]
            gap[todo] = dist[rows, best]
            todo = todo[~np.isfinite(gap[todo])]
        d = sections.travel[seg]
        cos = np.einsum("kj,kj->k", d, t) / np.maximum(np.linalg.norm(d, axis=1), 1e-300)
        decided = (gap <= reach) & sections.oriented[seg] & (np.abs(cos) >= MIN_SIGN_COS)
        return np.where(decided, np.sign(cos), 0.0)

    # -- fields ------------------------------------------------------------------------

    def bake_one(self, samples: SurfaceSamples, vertex: int, n_S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Field of one LED at membrane vertex `vertex` with unit normal `n_S` there.

        Returns fields (K, 3) float64 unit propagation directions and valid (K,) bool.
        """
        S = self.vertices[vertex]
        P = samples.points
        t, n_pl, ok = section_tangents(P, samples.normals, S, n_S)
        if not ok.any():
            return np.zeros_like(P), ok
        e_1, e_2 = pencil_frame(n_S)
        step = np.pi / N_PLANES
        psi = np.mod(np.arctan2(n_pl @ e_2, n_pl @ e_1), np.pi)  # (K,) rad, P's exact plane
        reach = FAR_TOLERANCE_EDGES * self.edge_length + np.linalg.norm(P - S, axis=1) * step
        # The two sampled planes that bracket P's plane must agree on the sign.
        k_lo = np.floor(psi / step).astype(np.int64) % N_PLANES
        k_hi = (k_lo + 1) % N_PLANES
        grid = np.unique(np.concatenate([k_lo[ok], k_hi[ok]]))
        sections = self.sections(vertex, e_1, e_2, grid * step)
        faces = samples.faces
        sign_lo = self.travel_signs(sections, np.searchsorted(grid, k_lo), P, faces, t, reach)
        sign_hi = self.travel_signs(sections, np.searchsorted(grid, k_hi), P, faces, t, reach)
        sign = np.where(sign_lo == sign_hi, sign_lo, 0.0)
        # Where they do not (a section changes topology, or the meeting point of two ways
        # round passes P, between them), slice P's own plane.
        redo = np.flatnonzero(ok & (sign == 0))
        if len(redo):
            exact, plane = np.unique(psi[redo], return_inverse=True)
            sections = self.sections(vertex, e_1, e_2, exact)
            sign[redo] = self.travel_signs(sections, plane, P[redo], faces[redo], t[redo], reach[redo])
        ok &= sign != 0
        return t * np.where(ok, sign, 0.0)[:, None], ok

    def bake(self, samples: SurfaceSamples, sources: Sources) -> tuple[np.ndarray, np.ndarray]:
        """Plane-section fields of every LED at every sample.

        Parameters
        ----------
        samples : SurfaceSamples, K membrane points (metres) with faces and unit normals.
        sources : Sources, L LEDs; uses their snapped vertices S and unit normals n_S there.

        Returns
        -------
        fields : (L, K, 3) float64, unit propagation directions (camera frame); zero where
            invalid.
        valid : (L, K) bool.
        """
        vertices, normals = _check_sources(sources, len(self.vertices))
        _check_samples(samples, len(self.faces))
        out = [self.bake_one(samples, int(v), n) for v, n in zip(vertices, normals)]
        return np.stack([f for f, _ in out]), np.stack([v for _, v in out])


def _check_sources(sources: Sources, n_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    vertices = np.asarray(sources.vertices)
    normals = np.asarray(sources.normals, dtype=np.float64)
    if vertices.ndim != 1 or vertices.dtype.kind not in "iu":
        raise ValueError(f"sources.vertices must be (L,) int vertex ids, got {vertices.shape} {vertices.dtype}")
    if vertices.size and (vertices.min() < 0 or vertices.max() >= n_vertices):
        raise ValueError(
            f"sources.vertices must be mesh vertex ids in [0, {n_vertices}), "
            f"got [{vertices.min()}, {vertices.max()}]"
        )
    if normals.shape != (len(vertices), 3):
        raise ValueError(f"sources.normals must be ({len(vertices)}, 3), got {normals.shape}")
    norm = np.linalg.norm(normals, axis=1)
    if not np.all(np.isfinite(normals)) or np.any(np.abs(norm - 1.0) > 1e-6):
        raise ValueError(f"sources.normals must be finite unit vectors, got norms {norm}")
    return vertices, normals / norm[:, None]


def _check_samples(samples: SurfaceSamples, n_faces: int) -> None:
    K = len(samples.points)
    if samples.points.shape != (K, 3) or samples.normals.shape != (K, 3) or samples.faces.shape != (K,):
        raise ValueError(
            f"samples must hold points (K, 3), normals (K, 3) and faces (K,), got "
            f"{samples.points.shape}, {samples.normals.shape}, {samples.faces.shape}"
        )
    if K and (samples.faces.min() < 0 or samples.faces.max() >= n_faces):
        raise ValueError(
            f"samples.faces must be face ids in [0, {n_faces}), got [{samples.faces.min()}, {samples.faces.max()}]"
        )


def bake_plane(mesh: trimesh.Trimesh, samples: SurfaceSamples, sources: Sources) -> tuple[np.ndarray, np.ndarray]:
    """One-off plane-section bake: (L, K, 3) unit fields, (L, K) valid."""
    return PlaneBaker(mesh).bake(samples, sources)
