"""Rig kinematics: the frames of the tapping rig, its servos' travel, and where the printer
head must be for a tap. Shared by the MuJoCo rig (``scenes.rig``), the protocols
(``scenes.protocol``) and the real rig (``rig/``), so that the simulated and the real
machine press the same way.

Frames and conventions:

- Sensor frame: the spec's camera frame, x right, y down, z forward along the sensor axis
  (towards the tip), metres.
- World frame: the printer bed, Z up. The sensor's axis lies along world +X (tip towards
  +X). At roll 0 the sensor frame maps to the world by :data:`SENSOR_TO_WORLD_AT_ROLL0`
  (x_s -> -Y, y_s -> -Z, z_s -> +X); the roll servo turns the sensor by ``roll`` about its
  own +z: ``world = SENSOR_TO_WORLD_AT_ROLL0 @ Rz(roll) @ v`` (:func:`sensor_to_world`),
  about the camera centre at :attr:`RigLayout.sensor_origin`. The sensor-frame direction
  facing world up is :func:`up_in_sensor`.
- The indenter points down (world -Z) at pitch 0; the pitch servo turns it about world
  +Y, so pitch theta points it along (-sin theta, 0, -cos theta) (:func:`indenter_axis`).
  Pitch pi/2 points it along -X, straight at the tip's apex.
- The printer head's position ``head`` (world, metres) is the MuJoCo rig's
  ``printer_x/y/z`` joints. The pitch servo's axis is ``mount_length`` below it and the
  indenter's base ``indenter_offset`` further along the indenter's axis; an indenter mesh
  has its feature along its local +z (``scenes.indenters``), turned to point down
  (:func:`indenter_to_world`).
- Printer coordinates are what G-code speaks: ``head - printer_origin``
  (:meth:`RigLayout.printer_position`), inside the build volume ``[0, build_volume]``.

A tap's ``normal`` (``scenes.taps.Tap``) is the direction the indenter comes from, in
the sensor frame; the roll and pitch servos realise exactly that direction
(:func:`normal_in_sensor`), and :func:`head_for_tap` puts the head where the indenter's
deepest point lies ``depth`` past the contact point along -normal.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

import numpy as np

# --- Frames ---------------------------------------------------------------------------

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
#: Largest deviation of a normal's length from 1.
UNIT_TOLERANCE = 1e-6


#: Servo travel, radians: the Hitec HS-422 turns about 180 degrees; a little beyond
#: [0, pi] for the roll and [0, pi/2] for the pitch leaves room for perturbed taps.
ROLL_TRAVEL_RAD = (-0.2, math.pi + 0.2)
PITCH_TRAVEL_RAD = (-0.35, math.pi / 2 + 0.35)

#: Joint names of the rig, in the order of a pose: the head's three axes (metres, world)
#: and the two servos (rad). A pose is a dict of these (the MuJoCo rig's joints).
JOINTS = ("printer_x", "printer_y", "printer_z", "indenter_pitch", "sensor_roll")


# --- Frames ---------------------------------------------------------------------------


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


def servo_angles(normal) -> tuple[np.ndarray, np.ndarray]:
    """The roll and pitch (rad) that aim the indenter along -normal, for any sensor-frame
    normal (N, 3) (the inverse of :func:`normal_in_sensor`).

    The roll turns the normal's part across the axis to face world up, and the pitch
    tilts the indenter from straight down towards the tip: roll atan2(-n_x, -n_y) (to a
    turn, from the roll's travel's start), pitch atan2(n_z, |n_xy|) in [-pi/2, pi/2]. Where that roll lies outside ROLL_TRAVEL_RAD,
    the roll half a turn away with the pitch past pi/2 (pi - pitch) aims the same way.
    Where neither lies within the servos' travel (ROLL_TRAVEL_RAD, PITCH_TRAVEL_RAD),
    the angles returned are the first pair; :func:`in_travel` says which can be reached.
    """
    n = np.atleast_2d(np.asarray(normal, dtype=np.float64))
    if n.shape[-1] != 3 or not np.all(np.isfinite(n)):
        raise ValueError(f"normal must be finite (N, 3), got shape {n.shape}")
    n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    across = np.hypot(n[..., 0], n[..., 1])
    lo = ROLL_TRAVEL_RAD[0]
    roll = lo + np.mod(np.arctan2(-n[..., 0], -n[..., 1]) - lo, 2 * math.pi)  # a turn from the travel's start
    pitch = np.arctan2(n[..., 2], across)
    turned = lo + np.mod(roll + math.pi - lo, 2 * math.pi)
    flip = ~in_travel(roll, pitch) & in_travel(turned, math.pi - pitch)
    return np.where(flip, turned, roll), np.where(flip, math.pi - pitch, pitch)


def in_travel(roll, pitch) -> np.ndarray:
    """(N,) bool, whether the roll and pitch servos can turn to these angles (rad)."""
    roll, pitch = np.asarray(roll, dtype=np.float64), np.asarray(pitch, dtype=np.float64)
    return (roll >= ROLL_TRAVEL_RAD[0]) & (roll <= ROLL_TRAVEL_RAD[1]) \
        & (pitch >= PITCH_TRAVEL_RAD[0]) & (pitch <= PITCH_TRAVEL_RAD[1])


# --- The machine -----------------------------------------------------------------------


def _rx_pi() -> np.ndarray:
    return np.diag([1.0, -1.0, -1.0])


def _ry(pitch) -> np.ndarray:
    """Rotations about +Y, (..., 3, 3)."""
    c, s = np.cos(pitch), np.sin(pitch)
    o, i = np.zeros_like(c), np.ones_like(c)
    return np.stack([np.stack([c, o, s], -1), np.stack([o, i, o], -1), np.stack([-s, o, c], -1)], -2)


def _indenter_turn(pitch) -> np.ndarray:
    """Rotation (..., 3, 3) of an indenter mesh into the world at a pitch: pointing down,
    then turned by the pitch servo."""
    return _ry(pitch) @ _rx_pi()


@dataclass(frozen=True)
class RigLayout:
    """Where the rig's parts are, metres (world frame).

    sensor_origin : the camera centre (the sensor frame's origin), about which it rolls.
    mount_length : from the head to the pitch servo's axis, straight down.
    indenter_offset : from the pitch axis to the indenter's base, along its axis.
    travel_x, travel_y, travel_z : the head's reach (the MuJoCo joints' ranges); at the
        lowest z, 85 mm above the bed, the pitch servo's indenters (20 mm long) stay 8 mm
        above the bed's top.
    home : the head's rest position, clear of the sensor.
    printer_origin : the head's world position at the printer's G-code zero (X0 Y0 Z0
        after homing); default the travel's lower corner, so printer coordinates run over
        [0, travel] on every axis.
    """

    sensor_origin: tuple[float, float, float] = (0.16, 0.0, 0.08)
    mount_length: float = 0.045
    indenter_offset: float = 0.012
    travel_x: tuple[float, float] = (-0.05, 0.35)
    travel_y: tuple[float, float] = (-0.16, 0.16)
    travel_z: tuple[float, float] = (0.085, 0.40)
    home: tuple[float, float, float] = (0.16, 0.0, 0.20)
    printer_origin: tuple[float, float, float] | None = None

    def __post_init__(self):
        for f in fields(self):
            value = getattr(self, f.name)
            if value is None:
                continue
            array = np.atleast_1d(np.asarray(value, dtype=np.float64))
            if not np.all(np.isfinite(array)):
                raise ValueError(f"rig layout {f.name} must be finite, got {value!r}")
            if f.name.startswith("travel_") and not (array.shape == (2,) and array[0] < array[1]):
                raise ValueError(f"rig layout {f.name} must be (low, high) with low < high metres, got {value!r}")
            if isinstance(value, (tuple, list)):
                object.__setattr__(self, f.name, tuple(float(v) for v in value))
        if self.printer_origin is None:
            object.__setattr__(self, "printer_origin", (self.travel_x[0], self.travel_y[0], self.travel_z[0]))

    @property
    def travel(self) -> np.ndarray:
        """(3, 2) the head's reach per axis, world metres."""
        return np.array([self.travel_x, self.travel_y, self.travel_z])

    def printer_position(self, head) -> np.ndarray:
        """Printer (G-code) coordinates, metres, of a world head position (3,)."""
        return np.asarray(head, dtype=np.float64) - np.asarray(self.printer_origin)

    def head_position(self, printer) -> np.ndarray:
        """World head position of printer coordinates (3,), metres."""
        return np.asarray(printer, dtype=np.float64) + np.asarray(self.printer_origin)

    def to_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, data, where: str = "rig layout") -> "RigLayout":
        """A layout from :meth:`to_dict`'s keys (any subset); ValueError naming a bad key."""
        if not isinstance(data, dict):
            raise ValueError(f"{where} must be a table of {[f.name for f in fields(cls)]}, got {type(data).__name__}")
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise ValueError(f"{where} has unknown keys {unknown}; it takes {sorted(names)}")
        try:
            return cls(**data)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{where}: {exc}") from None


def indenter_to_world(head, pitch: float, layout: RigLayout = RigLayout()) -> tuple[np.ndarray, np.ndarray]:
    """(R, t): an indenter mesh's frame in the world, with the head at ``head`` (3,) m and
    the pitch servo at ``pitch`` rad; world = R @ v + t for a mesh vertex v."""
    R = _indenter_turn(float(pitch))
    t = np.asarray(head, dtype=np.float64) + np.array([0.0, 0.0, -layout.mount_length]) \
        + _ry(float(pitch)) @ np.array([0.0, 0.0, -layout.indenter_offset])
    return R, t


def indenter_to_sensor(roll, pitch) -> np.ndarray:
    """Rotation from an indenter mesh's frame to the sensor frame at these servo angles:
    its local +z (the feature's direction) goes to -normal_in_sensor(roll, pitch).

    Parameters
    ----------
    roll, pitch : float or (N,) float, rad.

    Returns
    -------
    (3, 3) or (N, 3, 3) float64, ``sensor_to_world(roll).T @ R`` with R the rotation of
    :func:`indenter_to_world`.
    """
    return np.swapaxes(sensor_to_world(roll), -1, -2) @ _indenter_turn(np.asarray(pitch, dtype=np.float64))


def head_for_tap(tap, vertices: np.ndarray, layout: RigLayout = RigLayout()) -> np.ndarray:
    """Where the head must be, (3,) world metres, to press an indenter as a tap says.

    The indenter's tip (its mesh's top centre, ``(0, 0, max z)``) is put on the normal
    line through the contact point, and the head is moved along the normal until the
    indenter's deepest vertex lies ``tap.depth`` past the surface, measured along the
    normal.

    Parameters
    ----------
    tap : scenes.taps.Tap (point, normal, depth, sensor_roll, indenter_pitch).
    vertices : (V, 3) the indenter mesh's vertices, metres, its feature along local +z.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or len(vertices) == 0 or not np.all(np.isfinite(vertices)):
        raise ValueError(f"vertices must be a finite (V, 3) array with V > 0, got shape {vertices.shape}")
    R_s = sensor_to_world(tap.sensor_roll)
    p = R_s @ np.asarray(tap.point) + np.asarray(layout.sensor_origin)
    n = R_s @ np.asarray(tap.normal)
    R, t = indenter_to_world(np.zeros(3), tap.indenter_pitch, layout)
    verts = vertices @ R.T + t
    tip = R @ np.array([0.0, 0.0, vertices[:, 2].max()]) + t
    lateral = (p - tip) - np.dot(p - tip, n) * n
    along = (np.dot(p, n) - tap.depth) - (verts @ n).min()
    return lateral + along * n


def tap_pose(tap, vertices: np.ndarray, layout: RigLayout = RigLayout()) -> dict[str, float]:
    """The rig's joints (:data:`JOINTS`) that press a tap: :func:`head_for_tap` and its servo
    angles."""
    x, y, z = head_for_tap(tap, vertices, layout)
    return {"printer_x": float(x), "printer_y": float(y), "printer_z": float(z),
            "indenter_pitch": float(tap.indenter_pitch), "sensor_roll": float(tap.sensor_roll)}
