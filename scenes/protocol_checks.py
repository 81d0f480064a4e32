"""Safety checks of tapping protocols: how deep a tap may press, where its approach meets the
membrane, and :func:`validate`.

A tap (``scenes.taps.Tap``) is safe when its indenter stays clear of the glass core
(``scenes.body``, ``scenes.clearance``), its approach from outside meets the membrane at its
contact point, not too far off the membrane's normal, and the rig's servos reach and
realise that approach (``scenes.kinematics``).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence

import numpy as np
import trimesh

from .kinematics import PITCH_TRAVEL_RAD, ROLL_TRAVEL_RAD, UNIT_TOLERANCE, in_travel, normal_in_sensor
from .proximity import surface_distance
from .shapes import family
from .spec import SensorSpec
from .taps import Protocol, Tap

# --- Tolerances ---------------------------------------------------------------------

#: A contact point farther than this (metres) from where its approach ray meets the
#: membrane is not on the membrane (the mesh's chords sag ~3 um; 50 um is 2.5 % of a
#: 2 mm tap).
ON_MEMBRANE_TOLERANCE_M = 5e-5
#: How far (metres) a tap's indenter may reach past the glass core under its footprint
#: (scenes.clearance) before it is refused: float rounding only, as protocols cap their
#: taps to touch it at most.
CORE_CLEARANCE_TOLERANCE_M = 1e-6
#: Largest angle (rad) between the roll/pitch-realised approach and -normal.
SERVO_CONSISTENCY_TOLERANCE_RAD = 1e-6
#: Largest angle (rad) between a tap's approach and the membrane normal: beyond it the
#: indenter would slide along the membrane rather than press into it.
MAX_APPROACH_TILT_RAD = math.radians(20.0)

# --- Safe depths --------------------------------------------------------------------------


def max_safe_depth_m(spec: SensorSpec, points: np.ndarray | None = None, mesh: trimesh.Trimesh | None = None):
    """Deepest safe indentation, metres: the elastomer's thickness, past which the
    indenter would press on the glass core; under each of ``points`` (N, 3) on the
    membrane, or (None) the least anywhere (``scenes.body``; a body known in closed form,
    its family's ``tube``, is radius - core_radius thick everywhere)."""
    tube = family(spec.membrane.shape).tube(spec.membrane)
    if tube is not None:
        limit = float(tube.thickness)
        return limit if points is None else np.full(len(np.reshape(points, (-1, 3))), limit)
    from .body import sensor_body

    body = sensor_body(spec, mesh)
    return body.min_thickness if points is None else body.thickness_at(points)


@functools.lru_cache(maxsize=64)
def _paper_top_map(name: str, erosion: float):
    from .clearance import top_map
    from .indenters import make_indenter

    return top_map(make_indenter(name), erosion)


def _top_maps(objects, erosion: float) -> dict:
    """name -> scenes.clearance.TopMap of each indenter (a paper indenter's kept, a mesh
    file's read each time)."""
    from .clearance import top_map
    from .indenters import INDENTERS, indenter

    return {name: _paper_top_map(name, erosion) if name in INDENTERS else top_map(indenter(name), erosion)
            for name in sorted(set(objects))}


def core_safe_depth_m(spec: SensorSpec, mesh: trimesh.Trimesh, taps: Sequence[Tap]) -> np.ndarray:
    """How deep each tap may press before its indenter reaches the glass core, metres.

    The indenter is posed as the rig poses it (``scenes.kinematics.head_for_tap``) and
    measured over its whole footprint against the sensor's core (``scenes.body``,
    ``scenes.clearance``): where the membrane curves towards it, thins, or the approach
    tilts, that is shallower than the thickness under the contact point.

    Returns
    -------
    (N,) float64: each tap's own depth where its indenter stays clear of the core, else
    the depth at which it would touch it (<= 0 where it touches before it presses).
    """
    from .body import sensor_body
    from .clearance import core_clearance, core_erosion

    taps = list(taps)
    if not taps:
        return np.zeros(0)
    core = sensor_body(spec, mesh).core
    objects = [t.object for t in taps]
    depth = np.array([t.depth for t in taps], dtype=np.float64)
    clearance = core_clearance(
        core, [t.point for t in taps], [t.normal for t in taps], depth, [t.sensor_roll for t in taps],
        [t.indenter_pitch for t in taps], objects, _top_maps(objects, core_erosion(core)))
    return depth + clearance


# --- Approach rays and validation ---------------------------------------------------------


def approach_hits(mesh: trimesh.Trimesh, points: np.ndarray, normals: np.ndarray):
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


def surface_normals(mesh: trimesh.Trimesh, points: np.ndarray, face: np.ndarray) -> np.ndarray:
    """Interpolated vertex normals (N, 3) at points (N, 3) known to lie on faces (N,)."""
    bary = trimesh.triangles.points_to_barycentric(mesh.triangles[face], points)
    bary = np.clip(bary, 0.0, 1.0)
    bary /= bary.sum(axis=1, keepdims=True)
    n = (np.asarray(mesh.vertex_normals)[mesh.faces[face]] * bary[..., None]).sum(axis=1)
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def validate(protocol: Protocol, spec: SensorSpec, mesh: trimesh.Trimesh, *,
             safe: np.ndarray | None = None) -> None:
    """Check that every tap of a protocol can be carried out safely on a sensor.

    Raises ValueError naming the first failing tap (index, object, row, position) and
    how many fail, when a tap:

    - indents by depth <= 0 or past the elastomer's thickness under it
      (max_safe_depth_m; it would hit the glass core);
    - presses an indenter that would reach the glass core anywhere under its footprint
      (core_safe_depth_m), or names an object that is not an indenter;
    - has a normal that is not finite and unit;
    - approaches along a ray (from outside, along -normal) that misses the membrane;
    - has a contact point farther than ON_MEMBRANE_TOLERANCE_M from the membrane;
    - has a normal pointing into the membrane, or more than MAX_APPROACH_TILT_RAD off
      its normal;
    - is approached along a ray that meets the membrane before reaching the point;
    - needs servo angles past the servos' travel (the rig cannot reach it);
    - has servo angles (roll, pitch) that do not point the indenter along -normal.

    ``safe`` (N,) metres: the taps' :func:`core_safe_depth_m`, where the caller has them
    already (a protocol built by ``scenes.protocol`` is capped by them); else computed here.
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

    fail(~np.isfinite(depth) | (depth <= 0), lambda i: f"depth must be > 0 m, got {depth[i]!r}")
    finite = np.isfinite(point).all(axis=1) & np.isfinite(normal).all(axis=1)
    limit = np.full(len(taps), np.inf)
    limit[finite] = max_safe_depth_m(spec, point[finite], mesh)
    fail(
        depth > limit,
        lambda i: f"depth {depth[i]:.6g} m exceeds the safe maximum {limit[i]:.6g} m (the membrane's "
        "thickness under the contact): the indenter would hit the glass core",
    )
    finite &= np.isfinite(roll) & np.isfinite(pitch)
    fail(~finite, lambda i: "point, normal, sensor_roll and indenter_pitch must be finite")
    length = np.linalg.norm(normal, axis=1)
    fail(
        np.abs(length - 1.0) > UNIT_TOLERANCE, lambda i: f"normal must be a unit vector, got length {length[i]:.6g}"
    )

    hit, found, face = approach_hits(mesh, point, normal)
    fail(~found, lambda i: f"the approach ray along -normal {normal[i].round(4).tolist()} misses the membrane")
    gap = np.linalg.norm(hit - point, axis=1)
    off = gap > ON_MEMBRANE_TOLERANCE_M
    if off.any():
        # Say why: not on the membrane, an inward normal, or hidden behind another part.
        distance, closest, near_face = surface_distance(mesh, point[off])
        surface = surface_normals(mesh, closest, near_face)
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
    surface = surface_normals(mesh, hit, face)
    cos_tilt = np.clip(np.einsum("ij,ij->i", surface, normal / length[:, None]), -1.0, 1.0)
    fail(cos_tilt <= 0, lambda i: f"normal {normal[i].round(4).tolist()} points into the membrane")
    tilt = np.arccos(cos_tilt)
    fail(
        tilt > MAX_APPROACH_TILT_RAD,
        lambda i: f"the approach is {math.degrees(tilt[i]):.2f} deg off the membrane normal "
        f"(at most {math.degrees(MAX_APPROACH_TILT_RAD):.1f} deg): the indenter would slide",
    )
    reach = in_travel(roll, pitch)
    fail(~reach, lambda i: f"the rig cannot reach it: sensor_roll {roll[i]:.4g} rad and indenter_pitch {pitch[i]:.4g} "
         f"rad, past the servos' travel (roll {ROLL_TRAVEL_RAD[0]:.3g} to {ROLL_TRAVEL_RAD[1]:.3g} rad, pitch "
         f"{PITCH_TRAVEL_RAD[0]:.3g} to {PITCH_TRAVEL_RAD[1]:.3g} rad); no pair of servo angles aims the indenter along "
         f"this normal {normal[i].round(3).tolist()}")
    realised = normal_in_sensor(roll, pitch)
    chord = np.linalg.norm(realised - normal / length[:, None], axis=1)
    err = 2.0 * np.arcsin(np.clip(0.5 * chord, 0.0, 1.0))
    fail(
        err > SERVO_CONSISTENCY_TOLERANCE_RAD,
        lambda i: f"sensor_roll {roll[i]:.6g} rad and indenter_pitch {pitch[i]:.6g} rad point the indenter "
        f"{math.degrees(err[i]):.4f} deg away from -normal",
    )
    from .indenters import INDENTERS, is_indenter

    known = {o: is_indenter(o) for o in {t.object for t in taps}}
    fail(np.array([not known[t.object] for t in taps]),
         lambda i: f"object {taps[i].object!r} is none of the indenters {', '.join(INDENTERS)}, no ball "
                   "(ball_<diameter>mm) and no mesh file")
    safe = core_safe_depth_m(spec, mesh, taps) if safe is None else safe
    fail(
        depth > safe + CORE_CLEARANCE_TOLERANCE_M,
        lambda i: f"the {taps[i].object} indenter would reach {(depth[i] - safe[i]) * 1e3:.3f} mm into the glass "
        f"core under its footprint (it may press {max(safe[i], 0.0) * 1e3:.3f} mm here, not {depth[i] * 1e3:.3f} "
        "mm: the membrane curves towards it, thins or the approach tilts)",
    )
