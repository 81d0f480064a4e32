"""Tapping protocols: the base and extended sets of taps, where, how deep and from which
direction the indenters touch the sensor.

A protocol is data (``scenes.taps``: its :class:`Tap` and :class:`Protocol`); each one built
here is capped and checked by ``scenes.protocol_checks``. Contact points come from the
membrane's meridians (``scenes.meridian``), so any sensor shape works.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace

import numpy as np
import trimesh

from .kinematics import PITCH_TRAVEL_RAD, normal_in_sensor, pitch_for_normal, sensor_to_world, servo_angles
from .meridian import meridian, point_at_angle, point_at_arc, point_behind_junction
from .protocol_checks import approach_hits, core_safe_depth_m, surface_normals, validate
from .proximity import closest_faces
from .shapes import family
from .spec import SensorSpec
from .taps import Protocol, Tap

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
#: Any other membrane (a shape family other than the published GelTip's, whose
#: ``PUBLISHED`` is false: ``scenes.shapes``): each row's contacts are spread evenly in
#: arc length along its meridian, from the apex to this far (metres) before the camera
#: stops seeing it (the GelTip's EXTENDED_BASE_MARGIN_M leaves 2.5 mm past the 21.5 mm its
#: camera does not see), and aimed along the membrane's own normal.
SEEN_MARGIN_M = 0.0025
#: Any other membrane: a contact's aim is its normal's; where that needs a roll outside
#: ROLL_RANGE_RAD or a pitch below PITCH_RANGE_RAD (the servo horns' 0 to 180 deg at the
#: board's boot offsets, rig.servo_protocol.HORN_RANGE_CENTIDEG) by at most this, rad, the nearest
#: aim inside is taken (a tap tilted that far off the normal: the GelTip's extended
#: protocol jitters its servos by 3 deg); farther, the tap is left to be refused.
AIM_SLACK_RAD = math.radians(5.0)
#: Base protocol on any other membrane: contacts per row, as the GelTip's 4 + 2.
BASE_CONTACTS_PER_ROW = len(BASE_TIP_ANGLES_RAD) + len(BASE_CYLINDER_BACK_M)
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
#: Range of the pitch servo, rad, likewise: from 0 (its horn's 0 deg at the board's boot
#: offset, rig.servo_protocol.HORN_RANGE_CENTIDEG) to the end of its travel.
PITCH_RANGE_RAD = (0.0, PITCH_TRAVEL_RAD[1])

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
    at ``depth`` metres: 18 taps per object. On any other membrane than the published
    GelTip's (its family's ``PUBLISHED``: a capsule), each
    path's BASE_CONTACTS_PER_ROW contacts are spread evenly in arc length from the apex
    to SEEN_MARGIN_M before the camera stops seeing it, each aimed along the membrane's
    normal there (:func:`_contacts_any`): 18 taps per object as well.

    Parameters
    ----------
    spec : SensorSpec, for the safe depth.
    mesh : membrane mesh, sensor frame, metres.
    objects : indenter names (e.g. scenes.indenters.INDENTERS).
    depth : float, metres.

    Returns
    -------
    Protocol named "base", seed None, validated against the mesh; a tap whose indenter
    would reach the glass core under its footprint presses only until it touches it
    (:func:`core_safe_depth_m`).
    """
    objects = _check_objects(objects)
    if not family(spec.membrane.shape).PUBLISHED:
        point, normal, _ = _contacts_any(spec, mesh, BASE_ROLLS_RAD, BASE_CONTACTS_PER_ROW)
        rows = np.repeat(np.arange(len(BASE_ROLLS_RAD)), BASE_CONTACTS_PER_ROW)
        positions = np.tile(np.arange(BASE_CONTACTS_PER_ROW), len(BASE_ROLLS_RAD))
        point = point.reshape(-1, 3)
        roll, pitch = _aim(normal.reshape(-1, 3))
    else:
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
        point = np.vstack(points)
        pitch = np.concatenate([_nominal_pitch(r, n) for r, n in zip(BASE_ROLLS_RAD, normals)])
    normal = normal_in_sensor(roll, pitch)  # the membrane's normal, to rounding (or AIM_SLACK_RAD)
    n = len(point)
    per_tap = (rows, positions, np.zeros(n, int), roll, pitch, point, normal, np.full(n, float(depth)), np.zeros(n))
    taps = [tap for o, obj in enumerate(objects) for tap in _make_taps(obj, o * n, *per_tap)]
    taps, safe = _capped(taps, spec, mesh)
    protocol = Protocol(name="base", taps=taps, seed=None)
    validate(protocol, spec, mesh, safe=safe)
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
      tilt the approach off the membrane normal (reflected back into ROLL_RANGE_RAD and
      PITCH_RANGE_RAD, which the servo horns reach);
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
    Protocol named "extended" with 5 x 16 x replicas taps per object, validated; a tap
    whose indenter would reach the glass core under its footprint presses only until it
    touches it (:func:`core_safe_depth_m`).
    """
    objects = _check_objects(objects)
    if not isinstance(replicas, int) or isinstance(replicas, bool) or replicas < 1:
        raise ValueError(f"replicas must be an integer >= 1, got {replicas!r}")
    if not isinstance(seed, int) or isinstance(seed, bool):
        raise ValueError(f"seed must be an integer, got {seed!r}")
    rng = np.random.default_rng(seed)

    # Nominal contacts: one meridian per row.
    n_rows, n_contacts = len(EXTENDED_ROLLS_RAD), EXTENDED_CONTACTS_PER_ROW
    if not family(spec.membrane.shape).PUBLISHED:
        p0, n0, across = _contacts_any(spec, mesh, EXTENDED_ROLLS_RAD, n_contacts)
        roll0, pitch0 = (a.reshape(n_rows, n_contacts) for a in _aim(n0.reshape(-1, 3)))
        n0 = normal_in_sensor(roll0, pitch0)
    else:
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

    # Perturbed rolls are reflected back into ROLL_RANGE_RAD, or a nominal roll's side of it.
    lo = np.minimum(ROLL_RANGE_RAD[0], roll0)[None, :, :, None]
    hi = np.maximum(ROLL_RANGE_RAD[1], roll0)[None, :, :, None]
    roll = _reflect(roll0[None, :, :, None] + d_roll, lo, hi)
    # Perturbed pitches likewise into the horn's reach (>= 0: PITCH_RANGE_RAD): a cylinder
    # tap's nominal pitch is 0, and the servo board refuses a negative one.
    pitch = _reflect(pitch0[None, :, :, None] + d_pitch, np.minimum(PITCH_RANGE_RAD[0], pitch0)[None, :, :, None],
                     np.maximum(PITCH_RANGE_RAD[1], pitch0)[None, :, :, None])
    normal = normal_in_sensor(roll, pitch)
    # Tangent plane at the nominal contact: along the meridian and across it.
    across = np.broadcast_to(across[:, None, :], n0.shape)
    across = across - np.einsum("rci,rci->rc", across, n0)[..., None] * n0
    across = across / np.linalg.norm(across, axis=-1, keepdims=True)
    along = np.cross(across, n0)  # (rows, contacts, 3), unit
    cos_t, sin_t = (shift_r * np.cos(shift_t))[..., None], (shift_r * np.sin(shift_t))[..., None]
    target = p0[None, :, :, None] + cos_t * along[None, :, :, None, :] + sin_t * across[None, :, :, None, :]
    # The contact is where the shifted, tilted indenter axis first meets the membrane.
    point = target.copy()
    perturbed = np.broadcast_to(np.arange(replicas) > 0, shape)
    hit, found, _ = approach_hits(mesh, target[perturbed], normal[perturbed])
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
    taps, safe = _capped(taps, spec, mesh)
    protocol = Protocol(name="extended", taps=taps, seed=seed)
    validate(protocol, spec, mesh, safe=safe)
    return protocol


def _aim(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Roll and pitch (N,) that aim along normals (N, 3), nudged by up to AIM_SLACK_RAD
    into the rolls ROLL_RANGE_RAD and the pitches >= 0 the servo horns reach."""
    roll, pitch = servo_angles(normal)
    lo, hi = ROLL_RANGE_RAD
    roll = np.where((roll < lo) & (roll >= lo - AIM_SLACK_RAD), lo, roll)
    roll = np.where((roll > hi) & (roll <= hi + AIM_SLACK_RAD), hi, roll)
    low = PITCH_RANGE_RAD[0]
    pitch = np.where((pitch < low) & (pitch >= low - AIM_SLACK_RAD), low, pitch)
    return roll, pitch


def seen_arc(mer, camera) -> float:
    """Arc length along a meridian from its apex to where the camera stops seeing it
    (behind the camera or outside its image circle), metres."""
    from .camera import in_view

    lost = np.flatnonzero(~in_view(mer.points, camera))
    if len(lost) == 0:
        return mer.length
    return float(mer.arc[lost[0] - 1]) if lost[0] > 0 else 0.0


def _contacts_any(spec: SensorSpec, mesh: trimesh.Trimesh, rolls, count: int):
    """Contacts of rows along any membrane's meridians (SEEN_MARGIN_M, module doc).

    Returns points (R, C, 3) metres on the mesh, the membrane's outward normals there
    (R, C, 3) (interpolated vertex normals: off the meridian's plane where the membrane
    is not a surface of revolution) and each row's plane normal (R, 3).
    """
    from .camera import Camera

    camera = Camera.from_spec(spec)
    points, normals, across = [], [], []
    for roll in rolls:
        mer = meridian(mesh, roll)
        end = seen_arc(mer, camera) - SEEN_MARGIN_M
        if end <= 0:
            raise ValueError(f"mesh: the camera sees {seen_arc(mer, camera) * 1e3:.2f} mm of its meridian at roll {roll:g} "
                             f"rad from the apex, no more than SEEN_MARGIN_M = {SEEN_MARGIN_M * 1e3:g} mm: no room for taps")
        p, _ = point_at_arc(mer, np.linspace(0.0, end, count))
        face, _ = closest_faces(mesh, p)
        points.append(p)
        normals.append(surface_normals(mesh, p, face))
        across.append(mer.plane_normal)
    return np.stack(points), np.stack(normals), np.stack(across)


def _capped(taps: list[Tap], spec: SensorSpec, mesh: trimesh.Trimesh) -> tuple[tuple[Tap, ...], np.ndarray]:
    """The taps, each pressing no deeper than its indenter may before it touches the glass
    core, and their safe depths (:func:`core_safe_depth_m`: a capped tap's is the depth it
    now has, an uncapped one's its own, so they hold for the capped taps as well); a tap
    that cannot press at all is left for :func:`validate` to refuse."""
    safe = core_safe_depth_m(spec, mesh, taps)
    return tuple(replace(t, depth=float(d)) if 0.0 < d < t.depth else t for t, d in zip(taps, safe)), safe


def make_protocol(name: str, spec, mesh, objects, seed: int = 0) -> Protocol:
    """The protocol called ``name``: ``base`` (``base_protocol``) or ``extended``
    (``extended_protocol``, drawn with ``seed``), of ``objects`` on ``spec``'s ``mesh``."""
    if name == "base":
        return base_protocol(spec, mesh, objects)
    if name == "extended":
        return extended_protocol(spec, mesh, objects, seed=seed)
    raise ValueError(f"protocol must be 'base' or 'extended', got {name!r}")
