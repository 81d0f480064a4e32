"""Meridians: sections of a membrane mesh by planes through the sensor axis, where the
protocols put their contacts. Any sensor shape works: :func:`meridian` cuts the membrane
by the plane through the sensor axis and ``scenes.kinematics.up_in_sensor(roll)``, and
:func:`point_at_angle` / :func:`point_behind_junction` / :func:`point_at_arc` find points
on that section (sensor frame, metres).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from .kinematics import SENSOR_AXIS, up_in_sensor

#: Section endpoints closer than this (metres) are the same point of the meridian.
SECTION_MERGE_TOLERANCE_M = 1e-9
#: Interpolated vertex normals only reach 90 deg one mesh ring past a tip/cylinder
#: junction, so a normal within this of perpendicular to the axis counts as
#: perpendicular when locating the junction. On a tip whose meridian has radius of
#: curvature rho there, this moves the junction up to rho * tolerance towards the apex
#: (0.1 mm on the GelTip), which the one-ring blur largely cancels: the GelTip's comes
#: within 0.05 mm of the analytic one, where exactly 90 deg would put it ~0.5 mm down
#: the cylinder.
JUNCTION_ANGLE_TOLERANCE_RAD = math.radians(0.5)


@dataclass(frozen=True, eq=False)
class Meridian:
    """Section of the membrane by the plane through the sensor axis and up_in_sensor(roll),
    on the up side, from the apex (where it crosses the axis) to the membrane's open end.

    roll : float, rad.
    points : (K, 3) float64, metres, sensor frame, on the mesh (a polyline).
    arc : (K,) float64, metres, arc length from points[0], strictly increasing.
    angle : (K,) float64, rad, angle between the smooth outward normal (interpolated
        vertex normals, projected into the plane) and the axis, signed positive towards
        up: 0 at the apex, pi/2 on a cylinder.
    """

    roll: float
    points: np.ndarray
    arc: np.ndarray
    angle: np.ndarray

    @property
    def up(self) -> np.ndarray:
        """(3,) unit, the in-plane direction away from the axis (world up)."""
        return up_in_sensor(self.roll)

    @property
    def plane_normal(self) -> np.ndarray:
        """(3,) unit normal of the section plane: z x up."""
        return np.cross(SENSOR_AXIS, self.up)

    @property
    def length(self) -> float:
        """Arc length from the apex to the open end, metres."""
        return float(self.arc[-1])

    def normals(self, angle: np.ndarray) -> np.ndarray:
        """Unit in-plane normals (N, 3) at angles (N,) rad from the axis."""
        angle = np.asarray(angle, dtype=np.float64)[..., None]
        return np.sin(angle) * self.up + np.cos(angle) * SENSOR_AXIS


def _section_graph(mesh: trimesh.Trimesh, plane_normal: np.ndarray):
    """Section of a mesh by a plane through the origin, as merged nodes and edges."""
    lines, faces = trimesh.intersections.mesh_plane(mesh, plane_normal, np.zeros(3), return_faces=True)
    if len(lines) == 0:
        return None
    points = np.asarray(lines, dtype=np.float64).reshape(-1, 3)
    point_face = np.repeat(np.asarray(faces), 2)
    pairs = cKDTree(points).query_pairs(SECTION_MERGE_TOLERANCE_M, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(points),) * 2)
    _, label = connected_components(graph, directed=False)
    _, first = np.unique(label, return_index=True)
    edges = label.reshape(-1, 2)
    edges = edges[edges[:, 0] != edges[:, 1]]
    edges = np.unique(np.sort(edges, axis=1), axis=0)
    return points[first], point_face[first], edges


def _node_angles(mesh, nodes, node_face, up, plane_normal) -> np.ndarray:
    """Angle from the axis of the interpolated vertex normal at section nodes, rad."""
    # Barycentrics by hand: trimesh.proximity's closest point is unreliable at metre
    # scale (its tolerances are absolute), and the nodes are known to lie on their faces.
    bary = trimesh.triangles.points_to_barycentric(mesh.triangles[node_face], nodes)
    bary = np.clip(bary, 0.0, 1.0)
    bary /= bary.sum(axis=1, keepdims=True)
    normal = (np.asarray(mesh.vertex_normals)[mesh.faces[node_face]] * bary[..., None]).sum(axis=1)
    normal -= np.outer(normal @ plane_normal, plane_normal)
    return np.arctan2(normal @ up, normal @ SENSOR_AXIS)


def meridian(mesh: trimesh.Trimesh, roll: float) -> Meridian:
    """The membrane's meridian facing world up at a sensor roll.

    Parameters
    ----------
    mesh : membrane mesh in the sensor (camera) frame, metres, outward normals; any
        shape whose section by the plane is a simple curve crossing the sensor axis.
    roll : float, rad.

    Returns
    -------
    Meridian, from the section's crossing of the axis farthest along +z (the apex) to the
    membrane's open end (or the next crossing of the axis).
    """
    roll = float(roll)
    if not math.isfinite(roll):
        raise ValueError(f"roll must be finite, got {roll!r}")
    up = up_in_sensor(roll)
    plane_normal = np.cross(SENSOR_AXIS, up)
    section = _section_graph(mesh, plane_normal)
    if section is None:
        raise ValueError(f"mesh: the plane through the sensor axis at roll {roll:g} rad misses the membrane")
    nodes, node_face, edges = section
    degree = np.bincount(edges.ravel(), minlength=len(nodes))
    if degree.max() > 2:
        raise ValueError(
            f"mesh: its section at roll {roll:g} rad branches (a node joins {degree.max()} segments); "
            "the membrane must be a manifold surface"
        )
    neighbours: list[list[int]] = [[] for _ in nodes]
    for a, b in edges:
        neighbours[a].append(b)
        neighbours[b].append(a)
    u, z = nodes @ up, nodes @ SENSOR_AXIS
    angle = _node_angles(mesh, nodes, node_face, up, plane_normal)
    on_axis = np.abs(u) <= SECTION_MERGE_TOLERANCE_M

    # Where the section crosses the axis: at a node, or inside a segment.
    starts = []  # (z, point, angle, node before it, first node on the up side)
    for k in np.nonzero(on_axis)[0]:
        for nb in neighbours[k]:
            if u[nb] > SECTION_MERGE_TOLERANCE_M:
                starts.append((z[k], nodes[k], angle[k], k, nb))
    for a, b in edges:
        if on_axis[a] or on_axis[b] or u[a] * u[b] >= 0:
            continue
        a, b = (a, b) if u[a] < 0 else (b, a)
        t = u[a] / (u[a] - u[b])
        crossing = nodes[a] + t * (nodes[b] - nodes[a])
        starts.append((crossing @ SENSOR_AXIS, crossing, angle[a] + t * (angle[b] - angle[a]), a, b))
    if not starts:
        raise ValueError(f"mesh: its section at roll {roll:g} rad never crosses the sensor axis (no apex)")
    _, p0, a0, prev, cur = max(starts, key=lambda s: s[0])

    points, angles = [p0], [a0]
    while True:
        if u[cur] < -SECTION_MERGE_TOLERANCE_M:  # crossed the axis again: clip there
            t = u[prev] / (u[prev] - u[cur])
            points.append(nodes[prev] + t * (nodes[cur] - nodes[prev]))
            angles.append(angle[prev] + t * (angle[cur] - angle[prev]))
            break
        points.append(nodes[cur])
        angles.append(angle[cur])
        ahead = [n for n in neighbours[cur] if n != prev]
        if on_axis[cur] or not ahead or len(points) > len(nodes):
            break
        prev, cur = cur, ahead[0]

    points = np.asarray(points)
    angles = np.asarray(angles)
    step = np.linalg.norm(np.diff(points, axis=0), axis=1)
    keep = np.concatenate([[True], step > SECTION_MERGE_TOLERANCE_M])
    points, angles = points[keep], angles[keep]
    if len(points) < 2:
        raise ValueError(f"mesh: its meridian at roll {roll:g} rad is a single point")
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    return Meridian(roll=roll, points=points, arc=arc, angle=angles)


def arc_at_angle(mer: Meridian, angle) -> np.ndarray:
    """Arc length from the apex to the first point whose normal makes ``angle`` with the axis.

    Parameters
    ----------
    mer : Meridian.
    angle : float or (N,) float, rad, in [0, pi/2]. Angles within
        JUNCTION_ANGLE_TOLERANCE_RAD of pi/2 are taken as pi/2 minus that tolerance.

    Returns
    -------
    (N,) float64, metres (0 where the apex's own normal already reaches the angle).
    """
    angle = np.atleast_1d(np.asarray(angle, dtype=np.float64))
    if not np.all(np.isfinite(angle)) or np.any(angle < 0) or np.any(angle > math.pi / 2):
        raise ValueError(f"angle must be in [0, pi/2] rad, got {angle}")
    target = np.minimum(angle, math.pi / 2 - JUNCTION_ANGLE_TOLERANCE_RAD)
    running = np.maximum.accumulate(mer.angle)
    if target.max() > running[-1]:
        raise ValueError(
            f"no point of the meridian at roll {mer.roll:g} rad has its normal at "
            f"{math.degrees(target.max()):.2f} deg from the axis "
            f"(it reaches {math.degrees(running[-1]):.2f} deg)"
        )
    k = np.searchsorted(running, target, side="left")
    k0 = np.maximum(k - 1, 0)
    a0, a1 = mer.angle[k0], mer.angle[k]
    frac = np.where(k == 0, 0.0, (target - a0) / np.where(a1 > a0, a1 - a0, 1.0))
    return mer.arc[k0] + frac * (mer.arc[k] - mer.arc[k0])


def point_at_arc(mer: Meridian, arc) -> tuple[np.ndarray, np.ndarray]:
    """Points and smooth outward normals at arc lengths along a meridian.

    Parameters
    ----------
    mer : Meridian.
    arc : float or (N,) float, metres from the apex, in [0, mer.length].

    Returns
    -------
    points : (N, 3) float64, metres, sensor frame, on the mesh.
    normals : (N, 3) float64, unit, in the meridian plane.
    """
    arc = np.atleast_1d(np.asarray(arc, dtype=np.float64))
    if not np.all(np.isfinite(arc)) or np.any(arc < 0) or np.any(arc > mer.length):
        raise ValueError(
            f"arc must be in [0, {mer.length:.6g}] m along the meridian at roll {mer.roll:g} rad, got {arc}"
        )
    points = np.stack([np.interp(arc, mer.arc, mer.points[:, i]) for i in range(3)], axis=1)
    return points, mer.normals(np.interp(arc, mer.arc, mer.angle))


def junction_arc(mer: Meridian) -> float:
    """Arc length (metres) from the apex to where the tip meets the cylinder (normal at 90 deg)."""
    return float(arc_at_angle(mer, math.pi / 2)[0])


def point_at_angle(mer: Meridian, angle) -> tuple[np.ndarray, np.ndarray]:
    """Tip points whose outward normal makes ``angle`` (rad, [0, pi/2]) with the axis.

    Returns points (N, 3) metres on the mesh and normals (N, 3): exactly the requested
    angle, sin(angle) up + cos(angle) z.
    """
    angle = np.atleast_1d(np.asarray(angle, dtype=np.float64))
    points, _ = point_at_arc(mer, arc_at_angle(mer, angle))
    return points, mer.normals(angle)


def point_behind_junction(mer: Meridian, back) -> tuple[np.ndarray, np.ndarray]:
    """Points ``back`` metres of arc length past the tip junction, towards the open end.

    Returns points (N, 3) metres on the mesh and smooth normals (N, 3).
    """
    back = np.atleast_1d(np.asarray(back, dtype=np.float64))
    if np.any(back < 0):
        raise ValueError(f"back must be >= 0 m, got {back}")
    return point_at_arc(mer, junction_arc(mer) + back)
