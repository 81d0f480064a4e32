"""How far a posed indenter is from the glass core: the footprint test of a tap.

A tap's depth (``scenes.taps.Tap``) is measured at its contact point, along its
normal, and is safe there when it stays within the elastomer's thickness under that
point. Elsewhere under the indenter's footprint the membrane may curve towards the
indenter (a concave region: a waist, a saddle), the elastomer may be thinner, and a tilted
approach lowers one side of a flat indenter: an indenter pressed to a depth that is safe
at its contact point can still reach the glass a few millimetres away.

The *clearance* of a posed indenter is how much further it could travel along -normal
before any part of it touches the core; negative, how far it already reaches past it.

Method. In the indenter's own frame (``scenes.indenters``: feature along +z, tip at
``(0, 0, z_max)``) its top surface is a height map ``h(x, y) = z_max - z_top(x, y) >= 0``
below the tip, from rays cast along -z (inf where they miss). The rig poses an indenter
(``scenes.kinematics.head_for_tap``) with its tip at ``point - depth * normal`` and its
+z along -normal (``scenes.kinematics.indenter_to_sensor``, R), so a core vertex ``c``
lies at ``q = R^T (c - tip)`` in the tip's frame and the indenter can travel
``q_z + h(q_x, q_y)`` before it touches that vertex. The clearance is the least of that
over the core's vertices.

Between its vertices the core is flat faces. ``q_z`` is linear over a face, so its least
is at a vertex v, and every point x of the face lies within the face's longest edge of v.
With ``h`` eroded (its least over a disc, ``scipy.ndimage.grey_erosion``) by the core's
longest edge plus two map cells (one for the rays' grid, one for the nearest-cell lookup),
``q_z(x) + h(x) >= q_z(v) + h_eroded(v)``: the vertices' least bounds the whole surface's.
The test errs only towards caution, by the indenter's slope over that radius (none under a
flat face).

Speed. The core's vertices are grouped in cubes of :data:`CLUSTER_M`; a group is opened for
a tap only when its bounding sphere could reach above the indenter's surface over the
lateral distances it spans (:attr:`TopMap.floor`), so a tap on a convex membrane opens the
few groups right under its tip.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy import spatial

from .kinematics import indenter_to_sensor

#: Cell of an indenter's top height map, metres.
MAP_CELL_M = 1e-4
#: Edge of the cubes the core's vertices are grouped in, metres.
CLUSTER_M = 2e-3
#: Taps measured together (bounds the (groups x taps) arrays).
TAPS_PER_BATCH = 512
#: Slack of the groups' float32 bounds, metres (float32 rounds 0.1 m to 4e-9 m).
SLACK_M = 1e-6
#: Core vertices measured together against their taps.
POINTS_PER_BATCH = 2_000_000


@dataclass(frozen=True)
class TopMap:
    """An indenter's top surface seen from its tip, in its own frame.

    origin : (2,) float64, metres, (x, y) of cell [0, 0]'s centre.
    cell : float, metres.
    depth : (I, J) float64, metres, how far below the tip the surface lies (h, eroded as
        the module doc says); inf off the indenter.
    floor : (K,) float64, metres, the least of ``depth`` at lateral radii >= k * cell
        (inf past the last).
    z_max : float, metres, the tip's local z.
    """

    origin: np.ndarray
    cell: float
    depth: np.ndarray
    floor: np.ndarray
    z_max: float

    def __post_init__(self):
        for array in (self.origin, self.depth, self.floor):
            array.flags.writeable = False  # maps are kept and shared

    @property
    def reach(self) -> float:
        """How far from the tip (metres) any part of the surface in the map lies."""
        finite = np.isfinite(self.floor)
        if not finite.any():
            return 0.0
        lateral = (np.flatnonzero(finite).max() + 1) * self.cell
        return float(np.hypot(lateral, self.depth[np.isfinite(self.depth)].max()))

    def at(self, xy: np.ndarray) -> np.ndarray:
        """(M,) ``depth`` at lateral positions xy (M, 2), metres; inf off the map."""
        ij = np.floor((np.asarray(xy) - self.origin) / self.cell + 0.5).astype(np.int64)
        inside = (ij >= 0).all(axis=1) & (ij[:, 0] < self.depth.shape[0]) & (ij[:, 1] < self.depth.shape[1])
        out = np.full(len(ij), np.inf)
        out[inside] = self.depth[ij[inside, 0], ij[inside, 1]]
        return out

    def floor_at(self, radius: np.ndarray) -> np.ndarray:
        """The least ``depth`` at lateral radii >= ``radius`` (any shape, metres)."""
        k = np.floor(np.maximum(radius, 0.0) / self.cell).astype(np.int64)
        return np.where(k < len(self.floor), self.floor[np.minimum(k, len(self.floor) - 1)], np.inf)


def top_map(mesh: trimesh.Trimesh, erosion: float, cell: float = MAP_CELL_M) -> TopMap:
    """The top height map of an indenter mesh (feature along +z, metres), eroded by
    ``erosion`` metres plus two cells (module doc)."""
    from scipy import ndimage

    if not (np.isfinite(erosion) and erosion >= 0):
        raise ValueError(f"erosion must be >= 0 metres, got {erosion!r}")
    if not (np.isfinite(cell) and cell > 0):
        raise ValueError(f"cell must be > 0 metres, got {cell!r}")
    reach = int(np.ceil(erosion / cell)) + 2
    lo, hi = mesh.bounds
    pad = (reach + 1) * cell
    xs = np.arange(lo[0] - pad, hi[0] + pad + cell, cell)
    ys = np.arange(lo[1] - pad, hi[1] + pad + cell, cell)
    X, Y = np.meshgrid(xs, ys, indexing="ij")
    z_max = float(hi[2])
    origins = np.stack([X.ravel(), Y.ravel(), np.full(X.size, z_max + 1e-3)], axis=1)
    down = np.broadcast_to([0.0, 0.0, -1.0], origins.shape)
    _, ray, loc = mesh.ray.intersects_id(origins, down, multiple_hits=False, return_locations=True)
    depth = np.full(X.size, np.inf)
    depth[ray] = np.maximum(z_max - np.asarray(loc)[:, 2], 0.0)
    u, v = np.mgrid[-reach:reach + 1, -reach:reach + 1]
    depth = ndimage.grey_erosion(depth.reshape(X.shape), footprint=u**2 + v**2 <= reach**2, mode="constant",
                                 cval=np.inf)
    # floor[k]: the least depth over cells at radius >= k cells (a reversed running minimum).
    radius = np.hypot(X, Y)
    bins = np.floor(radius / cell).astype(np.int64).ravel()
    least = np.full(bins.max() + 1, np.inf)
    np.minimum.at(least, bins, depth.ravel())
    floor = np.minimum.accumulate(least[::-1])[::-1]
    return TopMap(np.array([xs[0], ys[0]]), float(cell), depth, floor, z_max)


@dataclass(frozen=True)
class _Groups:
    """A surface's points grouped in cubes: ``order[starts[j]:starts[j] + counts[j]]`` are
    group j's points, inside the sphere ``centres[j]``, ``radii[j]`` and within
    ``flatness[j]`` of the plane through the centre normal to the unit ``normals[j]``."""

    order: np.ndarray
    starts: np.ndarray
    counts: np.ndarray
    centres: np.ndarray
    radii: np.ndarray
    normals: np.ndarray
    flatness: np.ndarray


def _group(points: np.ndarray, normals: np.ndarray, size: float) -> _Groups:
    _, inverse = np.unique(np.floor(points / size).astype(np.int64), axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    order = np.argsort(inverse, kind="stable")
    counts = np.bincount(inverse)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])

    def mean(values):
        return np.stack([np.bincount(inverse, values[:, k]) for k in range(3)], axis=1) / counts[:, None]

    centres, m = mean(points), mean(normals)
    length = np.linalg.norm(m, axis=1, keepdims=True)
    m = np.where(length > 0, m / np.where(length > 0, length, 1.0), [0.0, 0.0, 1.0])
    offset = points - centres[inverse]
    radii, flatness = np.zeros(len(counts)), np.zeros(len(counts))
    np.maximum.at(radii, inverse, np.linalg.norm(offset, axis=1))
    np.maximum.at(flatness, inverse, np.abs(np.einsum("ij,ij->i", offset, m[inverse])))
    return _Groups(order, starts, counts, centres, radii, m, flatness)


def _expand(groups: _Groups, pair_group: np.ndarray):
    """(pair of each point, point index) for every point of each pair's group."""
    counts = groups.counts[pair_group]
    pair = np.repeat(np.arange(len(pair_group)), counts)
    offset = np.arange(len(pair)) - np.repeat(np.cumsum(counts) - counts, counts)
    return pair, groups.order[groups.starts[pair_group][pair] + offset]


def core_clearance(core: trimesh.Trimesh, point, normal, depth, roll, pitch, objects,
                   maps: dict[str, TopMap], upto: float = 0.0) -> np.ndarray:
    """The clearance of posed indenters over the glass core (module doc), metres.

    Parameters
    ----------
    core : the glass core's surface (``scenes.body.SensorBody.core``), sensor frame, metres.
    point, normal : (N, 3) float, the taps' contact points (metres) and unit normals.
    depth, roll, pitch : (N,) float, metres and rad: the taps' depths and servo angles.
    objects : (N,) str, each tap's indenter, a key of ``maps``.
    maps : name -> :class:`TopMap`, made with ``erosion`` >= the core's longest edge
        (:func:`core_erosion`).
    upto : float, metres: clearances of at least this are reported as ``upto``.

    Returns
    -------
    (N,) float64, metres: each tap's clearance where it is below ``upto``, else ``upto``.
    """
    point = np.asarray(point, dtype=np.float64).reshape(-1, 3)
    n = len(point)
    normal = np.asarray(normal, dtype=np.float64).reshape(n, 3)
    depth = np.asarray(depth, dtype=np.float64).reshape(n)
    objects = np.asarray(objects, dtype=object).reshape(n)
    missing = sorted(set(objects.tolist()) - set(maps))
    if missing:
        raise ValueError(f"objects {missing} have no top map; maps are given for {sorted(maps)}")
    out = np.full(n, float(upto))
    if n == 0:
        return out
    R = np.asarray(indenter_to_sensor(np.reshape(roll, n), np.reshape(pitch, n))).reshape(n, 3, 3)
    tip = point - depth[:, None] * normal
    vertices = np.asarray(core.vertices, dtype=np.float64)
    groups = _group(vertices, np.asarray(core.vertex_normals, dtype=np.float64), CLUSTER_M)
    tree = spatial.cKDTree(groups.centres)
    # Taps in cells of CLUSTER_M * 4, so that a batch's tips lie near each other.
    cells = np.floor(tip / (4 * CLUSTER_M)).astype(np.int64)
    for name in sorted(set(objects.tolist())):
        top = maps[name]
        mine = np.flatnonzero(objects == name)
        mine = mine[np.lexsort(cells[mine].T[::-1])]
        # No part of the indenter's top surface lies farther than this from its tip.
        reach = top.reach
        for batch in (mine[s:s + TAPS_PER_BATCH] for s in range(0, len(mine), TAPS_PER_BATCH)):
            t, nn = tip[batch], normal[batch]
            middle = t.mean(axis=0)
            span = float(np.linalg.norm(t - middle, axis=1).max())
            near = np.asarray(tree.query_ball_point(middle, reach + span + groups.radii.max()), dtype=np.int64)
            if len(near) == 0:
                continue
            centres, r = groups.centres[near].astype(np.float32), groups.radii[near, None]
            t32, n32 = t.astype(np.float32), nn.astype(np.float32)
            # How high above the tip plane each group can reach and how near the axis: with
            # p - c_j = a m_j + b (|a| <= flatness_j, b normal to m_j, |b| <= r_j), a point p
            # of group j lies (p - c_j).n <= flatness_j + r_j sin(n, m_j) above its centre
            # (float32, so SLACK_M keeps the bounds on the safe side).
            height = centres @ n32.T - np.einsum("ij,ij->i", t32, n32)  # (groups, taps)
            cos = groups.normals[near].astype(np.float32) @ n32.T
            rise = groups.flatness[near, None] + r * np.sqrt(np.maximum(1.0 - cos**2, 0.0))
            d2 = np.einsum("ij,ij->i", centres, centres)[:, None] - 2.0 * (centres @ t32.T) \
                + np.einsum("ij,ij->i", t32, t32)
            lateral = np.sqrt(np.maximum(d2 - height**2, 0.0))
            bound = top.floor_at(lateral - r - SLACK_M) - (height + rise + SLACK_M)
            g, k = np.nonzero(bound < out[batch])
            g = near[g]
            if len(g) == 0:
                continue
            # Open the groups in chunks of at most POINTS_PER_BATCH points.
            sizes = np.cumsum(groups.counts[g])
            edges = np.searchsorted(sizes, np.arange(POINTS_PER_BATCH, sizes[-1], POINTS_PER_BATCH))
            for part in np.split(np.arange(len(g)), edges):
                pair, vertex = _expand(groups, g[part])
                tap = batch[k[part][pair]]
                q = np.einsum("mji,mj->mi", R[tap], vertices[vertex] - tip[tap])
                np.minimum.at(out, tap, q[:, 2] + top.at(q[:, :2]))
    return out


def core_erosion(core: trimesh.Trimesh) -> float:
    """The erosion a top map needs for this core (module doc): its longest edge, metres."""
    return float(np.max(core.edges_unique_length)) if len(core.faces) else 0.0
