"""Tapping protocols: where, how deep and from which direction the indenters touch the sensor.

The real rig (and its MuJoCo twin) is a 3D printer whose head carries an indenter on a
pitch servo, with the sensor lying on the bed on a roll servo. A :class:`Tap` holds the
servo angles and the contact in the sensor frame; a :class:`Protocol` is an ordered,
JSON-serialisable tuple of taps.

Frames and conventions (shared with the rig, which imports them from here):

- Sensor frame: the spec's camera frame, x right, y down, z forward along the sensor axis
  (towards the tip), metres.
- World frame: the printer bed, Z up. The sensor's axis lies along world +X (tip towards
  +X). At roll 0 the sensor frame maps to the world by :data:`SENSOR_TO_WORLD_AT_ROLL0`
  (x_s -> -Y, y_s -> -Z, z_s -> +X); the roll servo turns the sensor by ``roll`` about its
  own +z: ``world = SENSOR_TO_WORLD_AT_ROLL0 @ Rz(roll) @ v`` (:func:`sensor_to_world`).
  The sensor-frame direction facing world up is :func:`up_in_sensor`.
- The indenter points down (world -Z) at pitch 0; the pitch servo turns it about world
  +Y, so pitch theta points it along (-sin theta, 0, -cos theta) (:func:`indenter_axis`).
  Pitch pi/2 points it along -X, straight at the tip's apex.

A tap's ``normal`` is the direction the indenter comes from, in the sensor frame: the
indenter moves along -normal, and the roll and pitch servos realise exactly that
direction (:func:`normal_in_sensor`). For an unperturbed tap it is the membrane's outward
normal at ``point``; a perturbed tap (roll and pitch offsets, shifted contact) approaches
up to a few degrees off the membrane normal, as the real rig would.

Contact points come from the membrane mesh, so any sensor shape works: :func:`meridian`
cuts the membrane by the plane through the sensor axis and :func:`up_in_sensor`, and
:func:`point_at_angle` / :func:`point_behind_junction` / :func:`point_at_arc` find
points on that section.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, fields

import numpy as np
import trimesh
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from .spec import SensorSpec

# --- Frames ------------------------------------------------------------------------

#: Rotation taking sensor-frame vectors to the world (bed) frame at sensor roll 0.
#: Columns: x_s -> -Y, y_s -> -Z, z_s -> +X (right-handed, det +1).
SENSOR_TO_WORLD_AT_ROLL0 = np.array(
    [
        [0.0, 0.0, 1.0],
        [-1.0, 0.0, 0.0],
        [0.0, -1.0, 0.0],
    ]
)
SENSOR_TO_WORLD_AT_ROLL0.setflags(write=False)

#: Sensor axis in the sensor frame (towards the tip), unit.
SENSOR_AXIS = np.array([0.0, 0.0, 1.0])
SENSOR_AXIS.setflags(write=False)

#: Largest |Y| of a unit world normal that the pitch servo can still face (it only
#: turns the indenter in the world XZ plane).
PITCH_PLANE_TOLERANCE = 1e-6

# --- Protocol constants -------------------------------------------------------------

#: Indentation of every tap, metres, along -normal (the paper's 2 mm).
TAP_DEPTH_M = 0.002
#: Base protocol: sensor rolls of its three paths, rad.
BASE_ROLLS_RAD = (0.0, math.pi / 2, math.pi)
#: Base protocol: angles between the tip taps' normals and the axis, rad (0 = apex,
#: pi/2 = where the tip meets the cylinder).
BASE_TIP_ANGLES_RAD = (0.0, math.radians(30.0), math.radians(60.0), math.pi / 2)
#: Base protocol: arc lengths of the cylinder taps back from the tip junction, metres.
BASE_CYLINDER_BACK_M = (0.009, 0.018)

#: Extended protocol: sensor rolls of its five rows, rad, spread over [0, pi].
EXTENDED_ROLLS_RAD = tuple(float(r) for r in np.linspace(0.0, math.pi, 5))
#: Extended protocol: contacts per row, from the apex along the meridian.
EXTENDED_CONTACTS_PER_ROW = 16
#: Extended protocol: the last contact of a row stays this far (arc length, metres)
#: from the membrane's open end. On the GelTip the camera sits 10 mm above the base and
#: sees the cylinder only from about 21.5 mm above it, so 24 mm keeps every contact in
#: view (the last one 20 mm back from the tip junction).
EXTENDED_BASE_MARGIN_M = 0.024
#: Extended protocol: replicas of every contact (replica 0 is unperturbed).
EXTENDED_REPLICAS = 36

# Perturbations of the extended protocol, each drawn uniformly in +- its magnitude
# (position: uniformly over a disc of that radius in the tangent plane).
#: Shift of the contact point along the surface, metres (contacts are ~2.5 mm apart).
POSITION_JITTER_M = 0.001
#: Offset of the sensor roll servo, rad; it tilts the approach across the meridian.
ROLL_JITTER_RAD = math.radians(3.0)
#: Offset of the indenter pitch servo, rad; it tilts the approach along the meridian.
PITCH_JITTER_RAD = math.radians(3.0)
#: Spin of the indenter about its own axis, rad.
SPIN_JITTER_RAD = math.radians(5.0)
#: Jitter of the commanded depth, metres (2 +- 0.25 mm stays below the 2.5 mm membrane).
DEPTH_JITTER_M = 0.00025
#: Range of the roll servo, rad; perturbed rolls are reflected back into it.
ROLL_RANGE_RAD = (0.0, math.pi)

# --- Tolerances ---------------------------------------------------------------------

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
#: A contact point farther than this (metres) from where its approach ray meets the
#: membrane is not on the membrane (the mesh's chords sag ~3 um; 50 um is 2.5 % of a
#: 2 mm tap).
ON_MEMBRANE_TOLERANCE_M = 5e-5
#: Largest deviation of a normal's length from 1.
UNIT_TOLERANCE = 1e-6
#: Largest angle (rad) between the roll/pitch-realised approach and -normal.
SERVO_CONSISTENCY_TOLERANCE_RAD = 1e-6
#: Largest angle (rad) between a tap's approach and the membrane normal: beyond it the
#: indenter would slide along the membrane rather than press into it.
MAX_APPROACH_TILT_RAD = math.radians(20.0)
#: Rounding of :meth:`Tap.pose_key`: lengths in metres and angles / unit vectors.
POSE_KEY_RESOLUTION_M = 1e-7
POSE_KEY_RESOLUTION_RAD = 1e-7

#: Version of the JSON layout written by :meth:`Protocol.to_dict`.
PROTOCOL_FORMAT_VERSION = 1


# --- Frames -------------------------------------------------------------------------


def _rz(roll: np.ndarray) -> np.ndarray:
    """Rotations about +z, (..., 3, 3)."""
    c, s = np.cos(roll), np.sin(roll)
    o, i = np.zeros_like(c), np.ones_like(c)
    return np.stack([np.stack([c, -s, o], -1), np.stack([s, c, o], -1), np.stack([o, o, i], -1)], -2)


def sensor_to_world(roll) -> np.ndarray:
    """Rotation from the sensor frame to the world frame at a sensor roll.

    Parameters
    ----------
    roll : float or (N,) float, rad, the roll servo angle.

    Returns
    -------
    (3, 3) or (N, 3, 3) float64: ``SENSOR_TO_WORLD_AT_ROLL0 @ Rz(roll)``.
    """
    return SENSOR_TO_WORLD_AT_ROLL0 @ _rz(np.asarray(roll, dtype=np.float64))


def up_in_sensor(roll) -> np.ndarray:
    """The sensor-frame direction that faces world up (+Z) at a sensor roll.

    Parameters
    ----------
    roll : float or (N,) float, rad.

    Returns
    -------
    (3,) or (N, 3) float64, unit: (-sin roll, -cos roll, 0).
    """
    roll = np.asarray(roll, dtype=np.float64)
    return np.stack([-np.sin(roll), -np.cos(roll), np.zeros_like(roll)], axis=-1)


def indenter_axis(pitch) -> np.ndarray:
    """World direction the indenter points along (its approach) at a pitch.

    Parameters
    ----------
    pitch : float or (N,) float, rad; 0 points down (-Z), pi/2 along -X.

    Returns
    -------
    (3,) or (N, 3) float64, unit: (-sin pitch, 0, -cos pitch).
    """
    pitch = np.asarray(pitch, dtype=np.float64)
    return np.stack([-np.sin(pitch), np.zeros_like(pitch), -np.cos(pitch)], axis=-1)


def normal_in_sensor(roll, pitch) -> np.ndarray:
    """The tap normal (the reversed indenter axis) that a roll and a pitch realise.

    Parameters
    ----------
    roll, pitch : float or (N,) float, rad.

    Returns
    -------
    (3,) or (N, 3) float64, unit, sensor frame: cos(pitch) up_in_sensor(roll) +
    sin(pitch) z.
    """
    world = -indenter_axis(pitch)
    return np.einsum("...ji,...j->...i", sensor_to_world(roll), world)


def pitch_for_normal(n_world) -> float | np.ndarray:
    """Pitch that points the indenter along -n_world.

    Parameters
    ----------
    n_world : (3,) or (N, 3) float, outward membrane normal in the world frame, in the
        XZ plane (the pitch servo cannot leave it; roll the sensor instead).

    Returns
    -------
    float or (N,) float, rad: atan2(n_x, n_z); a normal (cos a, 0, sin a) needs
    pi/2 - a, so the apex (+X) needs pi/2 and the top of the cylinder (+Z) needs 0.
    """
    n = np.asarray(n_world, dtype=np.float64)
    if n.shape[-1:] != (3,) or n.ndim > 2:
        raise ValueError(f"n_world must be (3,) or (N, 3), got shape {n.shape}")
    if not np.all(np.isfinite(n)):
        raise ValueError("n_world must be finite")
    length = np.linalg.norm(n, axis=-1)
    if np.any(length < UNIT_TOLERANCE):
        raise ValueError("n_world must be non-zero")
    off_plane = np.abs(n[..., 1]) / length
    if np.any(off_plane > PITCH_PLANE_TOLERANCE):
        raise ValueError(
            f"n_world must lie in the world XZ plane (the pitch servo turns about Y), got a "
            f"Y component of {float(np.max(off_plane)):.3g} of its length; roll the sensor instead"
        )
    pitch = np.arctan2(n[..., 0], n[..., 2])
    return float(pitch) if pitch.ndim == 0 else pitch


# --- Meridians on the membrane mesh ----------------------------------------------------


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


# --- Taps and protocols ---------------------------------------------------------------


@dataclass(frozen=True)
class Tap:
    """One tap of an indenter on the membrane.

    index : int, position in the protocol.
    object : str, indenter name.
    row : int, path (row) index within the object's taps.
    position : int, contact index along the row.
    replica : int, 0 for the unperturbed tap, > 0 for perturbed replicas.
    sensor_roll : float, rad, roll servo angle.
    indenter_pitch : float, rad, pitch servo angle.
    point : (3,) float, metres, contact point on the undeformed membrane, sensor frame.
    normal : (3,) float, unit, sensor frame: the indenter moves along -normal; the
        outward membrane normal at ``point`` for an unperturbed tap. Equal to
        ``normal_in_sensor(sensor_roll, indenter_pitch)``.
    depth : float, metres, indentation along -normal past ``point``.
    spin : float, rad, the indenter's rotation about its own axis.
    """

    index: int
    object: str
    row: int
    position: int
    replica: int
    sensor_roll: float
    indenter_pitch: float
    point: tuple[float, float, float]
    normal: tuple[float, float, float]
    depth: float
    spin: float = 0.0

    def __post_init__(self):
        for name in ("point", "normal"):
            value = getattr(self, name)
            if len(value) != 3:
                raise ValueError(f"tap {self.index}: {name} must have 3 components, got {value!r}")
            object.__setattr__(self, name, tuple(float(v) for v in value))

    @property
    def approach(self) -> np.ndarray:
        """(3,) unit direction the indenter moves along, sensor frame (-normal)."""
        return -np.asarray(self.normal)

    def pose_key(self) -> tuple:
        """Hashable, rounded description of the physical pose (object, servo angles,
        contact, depth, spin); two taps with the same key press the same way."""

        def q(values, resolution):
            return tuple(int(round(v / resolution)) for v in values)

        return (
            self.object,
            q((self.sensor_roll, self.indenter_pitch, self.spin), POSE_KEY_RESOLUTION_RAD),
            q(self.point + (self.depth,), POSE_KEY_RESOLUTION_M),
            q(self.normal, POSE_KEY_RESOLUTION_RAD),
        )

    def to_dict(self) -> dict:
        """JSON-ready dict (tuples as lists)."""
        out = {f.name: getattr(self, f.name) for f in fields(self)}
        out["point"], out["normal"] = list(self.point), list(self.normal)
        return out

    @classmethod
    def from_dict(cls, data, where: str = "tap") -> "Tap":
        """Build a tap from :meth:`to_dict`'s layout; ValueError naming the bad field."""
        if not isinstance(data, dict):
            raise ValueError(f"{where} must be an object, got {type(data).__name__}")
        names = [f.name for f in fields(cls)]
        unknown = sorted(set(data) - set(names))
        if unknown:
            raise ValueError(f"{where} has unknown keys {unknown}")
        values = {}
        for name in names:
            if name not in data:
                if name == "spin":
                    continue
                raise ValueError(f"{where} is missing {name!r}")
            value = data[name]
            if name == "object":
                if not isinstance(value, str) or not value:
                    raise ValueError(f"{where}.object must be a non-empty string, got {value!r}")
            elif name in ("index", "row", "position", "replica"):
                if not isinstance(value, int) or isinstance(value, bool) or value < 0:
                    raise ValueError(f"{where}.{name} must be an integer >= 0, got {value!r}")
            elif name in ("point", "normal"):
                if not isinstance(value, list) or len(value) != 3 or not all(_is_finite_number(v) for v in value):
                    raise ValueError(f"{where}.{name} must be a list of 3 finite numbers, got {value!r}")
                value = tuple(float(v) for v in value)
            else:
                if not _is_finite_number(value):
                    raise ValueError(f"{where}.{name} must be a finite number, got {value!r}")
                value = float(value)
            values[name] = value
        return cls(**values)


def _is_finite_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


@dataclass(frozen=True)
class Protocol:
    """An ordered set of taps.

    name : str, e.g. "base" or "extended".
    taps : tuple[Tap, ...], taps[i].index == i.
    seed : int or None, the seed its perturbations were drawn with (None: unperturbed).
    """

    name: str
    taps: tuple[Tap, ...]
    seed: int | None = None

    def __post_init__(self):
        if not isinstance(self.taps, tuple):
            object.__setattr__(self, "taps", tuple(self.taps))

    def __len__(self) -> int:
        return len(self.taps)

    @property
    def objects(self) -> tuple[str, ...]:
        """Indenter names, in order of first appearance."""
        return tuple(dict.fromkeys(t.object for t in self.taps))

    def to_dict(self) -> dict:
        return {
            "version": PROTOCOL_FORMAT_VERSION,
            "name": self.name,
            "seed": self.seed,
            "taps": [t.to_dict() for t in self.taps],
        }

    @classmethod
    def from_dict(cls, data) -> "Protocol":
        """Build a protocol from :meth:`to_dict`'s layout; ValueError naming what is wrong."""
        if not isinstance(data, dict):
            raise ValueError(f"protocol must be a JSON object, got {type(data).__name__}")
        unknown = sorted(set(data) - {"version", "name", "seed", "taps"})
        if unknown:
            raise ValueError(f"protocol has unknown keys {unknown}")
        version = data.get("version", PROTOCOL_FORMAT_VERSION)
        if version != PROTOCOL_FORMAT_VERSION:
            raise ValueError(f"protocol.version must be {PROTOCOL_FORMAT_VERSION}, got {version!r}")
        name = data.get("name")
        if not isinstance(name, str):
            raise ValueError(f"protocol.name must be a string, got {name!r}")
        seed = data.get("seed")
        if seed is not None and (not isinstance(seed, int) or isinstance(seed, bool)):
            raise ValueError(f"protocol.seed must be an integer or null, got {seed!r}")
        taps = data.get("taps")
        if not isinstance(taps, list):
            raise ValueError(f"protocol.taps must be a list, got {type(taps).__name__}")
        out = []
        for i, item in enumerate(taps):
            tap = Tap.from_dict(item, where=f"protocol.taps[{i}]")
            if tap.index != i:
                raise ValueError(f"protocol.taps[{i}].index must be {i}, got {tap.index}")
            out.append(tap)
        return cls(name=name, taps=tuple(out), seed=seed)

    def to_json(self, indent: int | None = None) -> str:
        return json.dumps(self.to_dict(), indent=indent, allow_nan=False)

    @classmethod
    def from_json(cls, text: str) -> "Protocol":
        try:
            data = json.loads(text)
        except (json.JSONDecodeError, TypeError) as exc:
            raise ValueError(f"protocol JSON could not be parsed: {exc}") from None
        return cls.from_dict(data)


# --- Building protocols --------------------------------------------------------------


def _check_objects(objects: Sequence[str]) -> tuple[str, ...]:
    if isinstance(objects, str) or not isinstance(objects, Sequence):
        raise ValueError(f"objects must be a sequence of indenter names, got {objects!r}")
    objects = tuple(objects)
    if not objects or not all(isinstance(o, str) and o for o in objects):
        raise ValueError(f"objects must be non-empty strings, got {objects!r}")
    if len(set(objects)) != len(objects):
        raise ValueError(f"objects must not repeat, got {objects!r}")
    return objects


def _nominal_pitch(roll: float, normals: np.ndarray) -> np.ndarray:
    """Pitches (N,) rad that face in-plane sensor normals (N, 3) at a roll."""
    world = normals @ sensor_to_world(roll).T
    world[:, 1] = 0.0  # in-plane by construction; drop rounding
    return np.asarray(pitch_for_normal(world)).reshape(-1)


def _make_taps(
    obj: str, start_index: int, rows, positions, replicas, roll, pitch, point, normal, depth, spin
) -> list[Tap]:
    """Taps of one object from flat per-tap arrays: rows, positions, replicas (N,) int;
    roll, pitch, depth, spin (N,) float; point, normal (N, 3) float."""
    columns = zip(
        np.asarray(rows).tolist(), np.asarray(positions).tolist(), np.asarray(replicas).tolist(),
        np.asarray(roll).tolist(), np.asarray(pitch).tolist(),
        map(tuple, np.asarray(point).tolist()), map(tuple, np.asarray(normal).tolist()),
        np.asarray(depth).tolist(), np.asarray(spin).tolist(),
    )
    return [Tap(start_index + k, obj, *values) for k, values in enumerate(columns)]


def base_protocol(
    spec: SensorSpec, mesh: trimesh.Trimesh, objects: Sequence[str], depth: float = TAP_DEPTH_M
) -> Protocol:
    """The paper's aligned real/sim set.

    For each object, three paths along the long axis with the sensor rolled by
    BASE_ROLLS_RAD; on each, tip taps at BASE_TIP_ANGLES_RAD and cylinder taps
    BASE_CYLINDER_BACK_M back from the tip junction, each perpendicular to the membrane
    at ``depth`` metres: 18 taps per object.

    Parameters
    ----------
    spec : SensorSpec, for the safe depth.
    mesh : membrane mesh, sensor frame, metres.
    objects : indenter names (e.g. scenes.indenters.INDENTERS).
    depth : float, metres.

    Returns
    -------
    Protocol named "base", seed None, validated against the mesh.
    """
    objects = _check_objects(objects)
    rows, positions, rolls, points, normals = [], [], [], [], []
    for row, roll in enumerate(BASE_ROLLS_RAD):
        mer = meridian(mesh, roll)
        tip_p, tip_n = point_at_angle(mer, BASE_TIP_ANGLES_RAD)
        cyl_p, cyl_n = point_behind_junction(mer, BASE_CYLINDER_BACK_M)
        p, n = np.vstack([tip_p, cyl_p]), np.vstack([tip_n, cyl_n])
        rows.append(np.full(len(p), row))
        positions.append(np.arange(len(p)))
        rolls.append(np.full(len(p), roll))
        points.append(p)
        normals.append(n)
    rows, positions, roll = np.concatenate(rows), np.concatenate(positions), np.concatenate(rolls)
    point, normal = np.vstack(points), np.vstack(normals)
    pitch = np.concatenate([_nominal_pitch(r, n) for r, n in zip(BASE_ROLLS_RAD, normals)])
    normal = normal_in_sensor(roll, pitch)  # equal to the meridian's, to rounding
    n = len(point)
    per_tap = (rows, positions, np.zeros(n, int), roll, pitch, point, normal, np.full(n, float(depth)), np.zeros(n))
    taps = [tap for o, obj in enumerate(objects) for tap in _make_taps(obj, o * n, *per_tap)]
    protocol = Protocol(name="base", taps=tuple(taps), seed=None)
    validate(protocol, spec, mesh)
    return protocol


def _reflect(values: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Reflect values that overshoot [lo, hi] by less than its width back into it."""
    values = np.where(values < lo, 2 * lo - values, values)
    return np.where(values > hi, 2 * hi - values, values)


def extended_protocol(
    spec: SensorSpec,
    mesh: trimesh.Trimesh,
    objects: Sequence[str],
    seed: int = 0,
    replicas: int = EXTENDED_REPLICAS,
    depth: float = TAP_DEPTH_M,
) -> Protocol:
    """The extended set: rows x contacts x replicas per object, with seeded perturbations.

    Five rows (sensor rolls EXTENDED_ROLLS_RAD), EXTENDED_CONTACTS_PER_ROW contacts per
    row spread evenly in arc length from the apex to EXTENDED_BASE_MARGIN_M before the
    membrane's open end, each replicated ``replicas`` times. Replica 0 is the nominal
    tap (perpendicular, at ``depth``); the others perturb, independently per object:

    - the contact, shifted along the surface (uniformly over a disc of radius
      POSITION_JITTER_M in the tangent plane) and re-projected onto the membrane along
      the approach;
    - the roll and pitch servos, by up to ROLL_JITTER_RAD and PITCH_JITTER_RAD, which
      tilt the approach off the membrane normal (rolls are kept in ROLL_RANGE_RAD);
    - the indenter's spin, by up to SPIN_JITTER_RAD;
    - the depth, by up to DEPTH_JITTER_M.

    Parameters
    ----------
    spec, mesh : the sensor and its membrane mesh (sensor frame, metres).
    objects : indenter names.
    seed : int, seeds the np.random.Generator of the perturbations.
    replicas : int >= 1.
    depth : float, metres, nominal depth.

    Returns
    -------
    Protocol named "extended" with 5 x 16 x replicas taps per object, validated.
    """
    objects = _check_objects(objects)
    if not isinstance(replicas, int) or isinstance(replicas, bool) or replicas < 1:
        raise ValueError(f"replicas must be an integer >= 1, got {replicas!r}")
    if not isinstance(seed, int) or isinstance(seed, bool):
        raise ValueError(f"seed must be an integer, got {seed!r}")
    rng = np.random.default_rng(seed)

    # Nominal contacts: one meridian per row.
    n_rows, n_contacts = len(EXTENDED_ROLLS_RAD), EXTENDED_CONTACTS_PER_ROW
    p0 = np.empty((n_rows, n_contacts, 3))
    n0 = np.empty((n_rows, n_contacts, 3))
    across = np.empty((n_rows, 3))
    for row, roll in enumerate(EXTENDED_ROLLS_RAD):
        mer = meridian(mesh, roll)
        end = mer.length - EXTENDED_BASE_MARGIN_M
        if end <= 0:
            raise ValueError(
                f"mesh: its meridian at roll {roll:g} rad is {mer.length:.4g} m long, shorter than "
                f"EXTENDED_BASE_MARGIN_M = {EXTENDED_BASE_MARGIN_M} m"
            )
        p0[row], n0[row] = point_at_arc(mer, np.linspace(0.0, end, n_contacts))
        across[row] = mer.plane_normal
    roll0 = np.broadcast_to(np.asarray(EXTENDED_ROLLS_RAD)[:, None], (n_rows, n_contacts))
    pitch0 = np.stack([_nominal_pitch(r, n) for r, n in zip(EXTENDED_ROLLS_RAD, n0)])

    # Perturbations, (objects, rows, contacts, replicas); replica 0 unperturbed.
    shape = (len(objects), n_rows, n_contacts, replicas)

    def jitter(magnitude: float) -> np.ndarray:
        values = rng.uniform(-magnitude, magnitude, shape)
        values[..., 0] = 0.0
        return values

    d_roll, d_pitch = jitter(ROLL_JITTER_RAD), jitter(PITCH_JITTER_RAD)
    spin, d_depth = jitter(SPIN_JITTER_RAD), jitter(DEPTH_JITTER_M)
    shift_r = POSITION_JITTER_M * np.sqrt(rng.uniform(0.0, 1.0, shape))
    shift_t = rng.uniform(0.0, 2 * math.pi, shape)
    shift_r[..., 0] = 0.0

    roll = _reflect(roll0[None, :, :, None] + d_roll, *ROLL_RANGE_RAD)
    pitch = pitch0[None, :, :, None] + d_pitch
    normal = normal_in_sensor(roll, pitch)
    # Tangent plane at the nominal contact: along the meridian and across it.
    along = np.cross(across[:, None, :], n0)  # (rows, contacts, 3), unit
    cos_t, sin_t = (shift_r * np.cos(shift_t))[..., None], (shift_r * np.sin(shift_t))[..., None]
    target = p0[None, :, :, None] + cos_t * along[None, :, :, None, :] + sin_t * across[None, :, None, None, :]
    # The contact is where the shifted, tilted indenter axis first meets the membrane.
    point = target.copy()
    perturbed = np.broadcast_to(np.arange(replicas) > 0, shape)
    hit, found, _ = _approach_hits(mesh, target[perturbed], normal[perturbed])
    if not found.all():
        bad = np.argwhere(perturbed)[np.argmin(found)]
        raise ValueError(
            f"a perturbed contact (object {objects[bad[0]]!r}, row {bad[1]}, position {bad[2]}, "
            f"replica {bad[3]}) misses the membrane; the perturbations are too large for this mesh"
        )
    point[perturbed] = hit
    depth_all = float(depth) + d_depth

    rows = np.broadcast_to(np.arange(n_rows)[:, None, None], shape[1:])
    positions = np.broadcast_to(np.arange(n_contacts)[None, :, None], shape[1:])
    reps = np.broadcast_to(np.arange(replicas)[None, None, :], shape[1:])
    taps = []
    for o, obj in enumerate(objects):
        taps += _make_taps(
            obj, len(taps), rows.ravel(), positions.ravel(), reps.ravel(), roll[o].ravel(), pitch[o].ravel(),
            point[o].reshape(-1, 3), normal[o].reshape(-1, 3), depth_all[o].ravel(), spin[o].ravel(),
        )
    protocol = Protocol(name="extended", taps=tuple(taps), seed=seed)
    validate(protocol, spec, mesh)
    return protocol


# --- Validation ---------------------------------------------------------------------------


def max_safe_depth_m(spec: SensorSpec) -> float:
    """Deepest safe indentation, metres: the membrane's thickness (radius - core_radius),
    past which the indenter would press on the glass core."""
    return float(spec.membrane.radius - spec.membrane.core_radius)


def _approach_hits(mesh: trimesh.Trimesh, points: np.ndarray, normals: np.ndarray):
    """Where rays from outside the mesh, along -normals through points, first meet it.

    Returns hits (N, 3) metres (points where missed), found (N,) bool, face (N,) int
    (-1 where missed).
    """
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    hits, found, face = points.copy(), np.zeros(len(points), bool), np.full(len(points), -1)
    if len(points) == 0:
        return hits, found, face
    # Start beyond the mesh's bounding box, so the first hit is seen from outside.
    lo, hi = mesh.bounds
    standoff = 2.0 * float(np.linalg.norm(hi - lo)) + float(np.max(np.abs(points - 0.5 * (lo + hi))))
    origins = points + standoff * normals
    tri, ray, loc = mesh.ray.intersects_id(origins, -normals, multiple_hits=False, return_locations=True)
    if len(ray):
        t = np.einsum("ij,ij->i", np.asarray(loc) - origins[ray], -normals[ray])
        hits[ray] = origins[ray] - t[:, None] * normals[ray]  # snap onto the ray (Embree is float32)
        found[ray] = True
        face[ray] = tri
    return hits, found, face


def _surface_normals(mesh: trimesh.Trimesh, points: np.ndarray, face: np.ndarray) -> np.ndarray:
    """Interpolated vertex normals (N, 3) at points (N, 3) known to lie on faces (N,)."""
    bary = trimesh.triangles.points_to_barycentric(mesh.triangles[face], points)
    bary = np.clip(bary, 0.0, 1.0)
    bary /= bary.sum(axis=1, keepdims=True)
    n = (np.asarray(mesh.vertex_normals)[mesh.faces[face]] * bary[..., None]).sum(axis=1)
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def _distance_to_mesh(mesh: trimesh.Trimesh, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest points, distances and faces, computed in millimetres.

    trimesh.proximity's tolerances are absolute and misplace closest points on meshes
    in metres (by up to ~0.3 mm on the GelTip mesh), so query a copy scaled to mm.
    """
    scaled = trimesh.Trimesh(np.asarray(mesh.vertices) * 1e3, mesh.faces, process=False)
    closest, distance, face = trimesh.proximity.closest_point(scaled, np.asarray(points) * 1e3)
    return closest * 1e-3, distance * 1e-3, face


def validate(protocol: Protocol, spec: SensorSpec, mesh: trimesh.Trimesh) -> None:
    """Check that every tap of a protocol can be carried out safely on a sensor.

    Raises ValueError naming the first failing tap (index, object, row, position) and
    how many fail, when a tap:

    - indents by depth <= 0 or past max_safe_depth_m(spec) (it would hit the glass core);
    - has a normal that is not finite and unit;
    - approaches along a ray (from outside, along -normal) that misses the membrane;
    - has a contact point farther than ON_MEMBRANE_TOLERANCE_M from the membrane;
    - has a normal pointing into the membrane, or more than MAX_APPROACH_TILT_RAD off
      its normal;
    - is approached along a ray that meets the membrane before reaching the point;
    - has servo angles (roll, pitch) that do not point the indenter along -normal.
    """
    if not isinstance(protocol, Protocol):
        raise ValueError(f"protocol must be a Protocol, got {type(protocol).__name__}")
    taps = protocol.taps
    if not taps:
        return
    depth = np.array([t.depth for t in taps])
    point = np.array([t.point for t in taps])
    normal = np.array([t.normal for t in taps])
    roll = np.array([t.sensor_roll for t in taps])
    pitch = np.array([t.indenter_pitch for t in taps])

    def fail(bad: np.ndarray, why) -> None:
        idx = np.nonzero(bad)[0]
        if len(idx) == 0:
            return
        i = int(idx[0])
        t = taps[i]
        more = f" ({len(idx) - 1} more taps fail the same way)" if len(idx) > 1 else ""
        raise ValueError(
            f"{protocol.name} tap {t.index} (object {t.object!r}, row {t.row}, position {t.position}, "
            f"replica {t.replica}): {why(i)}{more}"
        )

    limit = max_safe_depth_m(spec)
    fail(~np.isfinite(depth) | (depth <= 0), lambda i: f"depth must be > 0 m, got {depth[i]!r}")
    fail(
        depth > limit,
        lambda i: f"depth {depth[i]:.6g} m exceeds the safe maximum {limit:.6g} m (the membrane's "
        "thickness, radius - core_radius): the indenter would hit the glass core",
    )
    finite = np.isfinite(point).all(axis=1) & np.isfinite(normal).all(axis=1)
    finite &= np.isfinite(roll) & np.isfinite(pitch)
    fail(~finite, lambda i: "point, normal, sensor_roll and indenter_pitch must be finite")
    length = np.linalg.norm(normal, axis=1)
    fail(
        np.abs(length - 1.0) > UNIT_TOLERANCE, lambda i: f"normal must be a unit vector, got length {length[i]:.6g}"
    )

    hit, found, face = _approach_hits(mesh, point, normal)
    fail(~found, lambda i: f"the approach ray along -normal {normal[i].round(4).tolist()} misses the membrane")
    gap = np.linalg.norm(hit - point, axis=1)
    off = gap > ON_MEMBRANE_TOLERANCE_M
    if off.any():
        # Say why: not on the membrane, an inward normal, or hidden behind another part.
        closest, distance, near_face = _distance_to_mesh(mesh, point[off])
        surface = _surface_normals(mesh, closest, near_face)
        dist = np.zeros(len(taps))
        dist[off] = distance
        fail(
            dist > ON_MEMBRANE_TOLERANCE_M,
            lambda i: f"point {point[i].round(6).tolist()} m is {dist[i] * 1e3:.3f} mm from the membrane "
            f"(tolerance {ON_MEMBRANE_TOLERANCE_M * 1e3:.3f} mm): the tap would miss the sensor",
        )
        facing = np.ones(len(taps))
        facing[off] = np.einsum("ij,ij->i", surface, normal[off])
        fail(facing <= 0, lambda i: f"normal {normal[i].round(4).tolist()} points into the membrane")
        fail(
            off,
            lambda i: f"the approach along -normal meets the membrane {gap[i] * 1e3:.3f} mm "
            "before the contact point",
        )
    surface = _surface_normals(mesh, hit, face)
    cos_tilt = np.clip(np.einsum("ij,ij->i", surface, normal / length[:, None]), -1.0, 1.0)
    fail(cos_tilt <= 0, lambda i: f"normal {normal[i].round(4).tolist()} points into the membrane")
    tilt = np.arccos(cos_tilt)
    fail(
        tilt > MAX_APPROACH_TILT_RAD,
        lambda i: f"the approach is {math.degrees(tilt[i]):.2f} deg off the membrane normal "
        f"(at most {math.degrees(MAX_APPROACH_TILT_RAD):.1f} deg): the indenter would slide",
    )
    realised = normal_in_sensor(roll, pitch)
    chord = np.linalg.norm(realised - normal / length[:, None], axis=1)
    err = 2.0 * np.arcsin(np.clip(0.5 * chord, 0.0, 1.0))
    fail(
        err > SERVO_CONSISTENCY_TOLERANCE_RAD,
        lambda i: f"sensor_roll {roll[i]:.6g} rad and indenter_pitch {pitch[i]:.6g} rad point the indenter "
        f"{math.degrees(err[i]):.4f} deg away from -normal",
    )
