"""Taps and tapping protocols as data: :class:`Tap`, :class:`Protocol` and their JSON form.

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
would.

Protocols are built by ``scenes.protocol`` and checked by ``scenes.protocol_checks``.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, fields

import numpy as np

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
