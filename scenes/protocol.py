"""Tapping protocols: where, how deep and from which direction the indenters touch the sensor.

The real rig (and its MuJoCo twin) is a 3D printer whose head carries an indenter on a
pitch servo, with the sensor lying on the bed on a roll servo. A :class:`Tap` holds the
servo angles and the contact in the sensor frame; a :class:`Protocol` is an ordered,
JSON-serialisable tuple of taps.

The frames, servo angles and head positions are the rig's kinematics
(``scenes.kinematics``). A tap's ``normal`` is the direction the indenter comes from, in
the sensor frame: the indenter moves along -normal, and the roll and pitch servos realise
exactly that direction (``scenes.kinematics.normal_in_sensor``). For an unperturbed tap it
is the membrane's outward normal at ``point``; a perturbed tap (roll and pitch offsets,
shifted contact) approaches up to a few degrees off the membrane normal, as the real rig
would. Contact points come from the membrane's meridians (``scenes.meridian``), so any
sensor shape works.
"""

from __future__ import annotations

import functools
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass, fields, replace

import numpy as np
import trimesh

from .kinematics import (PITCH_TRAVEL_RAD, ROLL_TRAVEL_RAD, UNIT_TOLERANCE, in_travel, normal_in_sensor,
                         pitch_for_normal, sensor_to_world, servo_angles)
from .meridian import meridian, point_at_angle, point_at_arc, point_behind_junction
from .spec import SensorSpec

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
#: Any other membrane (``spec.membrane.shape`` not "capsule"): each row's contacts are
#: spread evenly in arc length along its meridian, from the apex to this far (metres)
#: before the camera stops seeing it (the GelTip's EXTENDED_BASE_MARGIN_M leaves 2.5 mm
#: past the 21.5 mm its camera does not see), and aimed along the membrane's own normal.
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
#: Rounding of :meth:`Tap.pose_key`: lengths in metres and angles / unit vectors.
POSE_KEY_RESOLUTION_M = 1e-7
POSE_KEY_RESOLUTION_RAD = 1e-7

#: Version of the JSON layout written by :meth:`Protocol.to_dict`.
PROTOCOL_FORMAT_VERSION = 1


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
    at ``depth`` metres: 18 taps per object. On any other membrane than a capsule, each
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
    if spec.membrane.shape != "capsule":
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
    _validate(protocol, spec, mesh, safe)
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
    if spec.membrane.shape != "capsule":
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
    taps, safe = _capped(taps, spec, mesh)
    protocol = Protocol(name="extended", taps=taps, seed=seed)
    _validate(protocol, spec, mesh, safe)
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
    from .body import closest_faces
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
        normals.append(_surface_normals(mesh, p, face))
        across.append(mer.plane_normal)
    return np.stack(points), np.stack(normals), np.stack(across)


# --- Validation ---------------------------------------------------------------------------


def max_safe_depth_m(spec: SensorSpec, points: np.ndarray | None = None, mesh: trimesh.Trimesh | None = None):
    """Deepest safe indentation, metres: the elastomer's thickness, past which the
    indenter would press on the glass core; under each of ``points`` (N, 3) on the
    membrane, or (None) the least anywhere (``scenes.body``; a capsule's is
    radius - core_radius everywhere)."""
    if spec.membrane.shape == "capsule":
        limit = float(spec.membrane.radius - spec.membrane.core_radius)
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


def _capped(taps: list[Tap], spec: SensorSpec, mesh: trimesh.Trimesh) -> tuple[tuple[Tap, ...], np.ndarray]:
    """The taps, each pressing no deeper than its indenter may before it touches the glass
    core, and their safe depths (:func:`core_safe_depth_m`: a capped tap's is the depth it
    now has, an uncapped one's its own, so they hold for the capped taps as well); a tap
    that cannot press at all is left for :func:`validate` to refuse."""
    safe = core_safe_depth_m(spec, mesh, taps)
    return tuple(replace(t, depth=float(d)) if 0.0 < d < t.depth else t for t, d in zip(taps, safe)), safe


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


def validate(protocol: Protocol, spec: SensorSpec, mesh: trimesh.Trimesh) -> None:
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
    """
    _validate(protocol, spec, mesh)


def _validate(protocol: Protocol, spec: SensorSpec, mesh: trimesh.Trimesh, safe: np.ndarray | None = None) -> None:
    """:func:`validate`, given the taps' core_safe_depth_m where they are known."""
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

    hit, found, face = _approach_hits(mesh, point, normal)
    fail(~found, lambda i: f"the approach ray along -normal {normal[i].round(4).tolist()} misses the membrane")
    gap = np.linalg.norm(hit - point, axis=1)
    off = gap > ON_MEMBRANE_TOLERANCE_M
    if off.any():
        # Say why: not on the membrane, an inward normal, or hidden behind another part.
        from .body import surface_distance

        distance, closest, near_face = surface_distance(mesh, point[off])
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
