"""The servo board's line protocol as pure functions over text: commands, framing, replies.

The rig's Arduino Mega (``rig/firmware/servo_rig/servo_rig.ino``) drives two hobby servos:
``R``, the sensor's roll servo (``sensor_roll``), and ``P``, the indenter's pitch servo
(``indenter_pitch``). Radians exist on the host; on the wire angles are degrees with two
decimals (``-11.45``), which the board reads as integer centidegrees. Nothing here touches a
port; :mod:`rig.servos` carries these lines over pyserial and :mod:`rig.twins.servos` answers
them on a pty.

Lines (ASCII, ended by ``\\n``; the board also accepts ``\\r``; empty lines are ignored):

* Every line, both ways, is framed ``<body>*<checksum>``, the checksum being Marlin's: the
  XOR of the body's bytes as a decimal number (:func:`rig.gcode.checksum`).
* Host to board, one command in flight at a time:

  ========================  =========================================  ===========================
  command                   meaning                                    answer
  ========================  =========================================  ===========================
  ``H``                     hello                                      ``OK H servo_rig <version>``
  ``S <id> <angle_deg>``    move servo ``id`` (``R``/``P``) to angle   ``OK S <id> <angle_deg>``
  ``? <id>``                last angle set on servo ``id``             ``OK ? <id> <angle_deg>``
  ``C <id> <offset_deg>``   set servo ``id``'s calibration offset      ``OK C <id> <offset_deg>``
  ========================  =========================================  ===========================

* A refusal is ``ERR <code> <message>`` (:class:`Code`). The board clamps nothing: an angle
  outside the servo's travel (:data:`ROLL`, :data:`PITCH`, from :mod:`scenes.kinematics`) is
  ``ERR 5``; an angle whose horn angle (angle + offset) is outside the Servo library's
  0-180 degree pulse range is ``ERR 6``; an offset beyond :data:`MAX_OFFSET_CENTIDEG` is
  ``ERR 7``; ``?`` before any ``S`` is ``ERR 8`` (the board does not drive a servo, which
  would jump on attach, until told where to go).
* On boot (the Mega resets when the port is opened) the board sends ``READY servo_rig
  <version>``. Offsets then hold the sketch's constants; ``C`` changes them until reset.

Why a checksum and no sequence number: every command is idempotent (an absolute angle, an
absolute offset, or a read), so running a line twice is harmless and the host can simply
write the same line again on any doubt: a corrupted command (``ERR 1``, or ``ERR 2`` for a
line too long, e.g. a lost line break), a corrupted reply (bad checksum) or no reply. The
checksum runs both ways so that a corrupted reply is never taken for an answer, and every
``OK`` echoes its command, so a late answer to an earlier attempt is recognised and skipped
instead of being taken for the current one. A sequence number would add state that a board
reset loses, to protect against duplicates that do no harm. The XOR checksum misses errors
that cancel out (two flipped copies of one bit); the echo check catches most of those in
replies, and the board's syntax and range checks catch most in commands.
"""

from __future__ import annotations

import enum
import math
import re
from dataclasses import dataclass

from rig.gcode import checksum
from scenes.kinematics import PITCH_TRAVEL_RAD, ROLL_TRAVEL_RAD

#: Name the board gives itself in its banner and its answer to ``H``.
FIRMWARE = "servo_rig"
#: Version of this protocol; the sketch's must match.
PROTOCOL_VERSION = 1
#: First word of the boot banner.
BANNER_WORD = "READY"
#: Centidegrees per degree: angles travel as degrees with two decimals.
CENTIDEG_PER_DEG = 100
#: Longest line the board buffers, bytes, without its line break (the sketch's buffer).
MAX_LINE_BYTES = 31
#: Largest calibration offset, centidegrees (20 degrees: a horn a tooth or two off).
MAX_OFFSET_CENTIDEG = 2000
#: Horn angles the Servo library maps to pulses, centidegrees (its ``write()`` range).
HORN_RANGE_CENTIDEG = (0, 18000)
#: Pulse widths at those horn angles, microseconds (Servo.h's MIN_ and MAX_PULSE_WIDTH).
PULSE_RANGE_US = (544, 2400)


class Code(enum.IntEnum):
    """Codes of ``ERR <code> <message>`` replies."""

    CHECKSUM = 1  # missing or wrong checksum: write the line again
    OVERFLOW = 2  # line longer than MAX_LINE_BYTES: write the line again
    SYNTAX = 3  # unknown command or malformed argument
    SERVO = 4  # unknown servo id
    TRAVEL = 5  # angle outside the servo's travel
    PULSE = 6  # angle + offset outside the horn's pulse range
    OFFSET = 7  # offset beyond MAX_OFFSET_CENTIDEG
    UNSET = 8  # `?` on a servo that was never set


#: Codes that say the line was damaged on the way, not refused: the host writes it again.
TRANSMISSION_ERRORS = frozenset({Code.CHECKSUM, Code.OVERFLOW})


@dataclass(frozen=True)
class Servo:
    """One servo of the board: its wire id, its joint name and its travel."""

    wire_id: str  # one letter on the wire
    name: str  # joint name in scenes.rig's MuJoCo model
    travel_rad: tuple[float, float]  # (min, max) angle, radians

    @property
    def travel_centideg(self) -> tuple[int, int]:
        """Travel in whole centidegrees, rounded inwards (what the sketch holds)."""
        lo, hi = (math.degrees(a) * CENTIDEG_PER_DEG for a in self.travel_rad)
        return math.ceil(lo), math.floor(hi)


ROLL = Servo("R", "sensor_roll", ROLL_TRAVEL_RAD)
PITCH = Servo("P", "indenter_pitch", PITCH_TRAVEL_RAD)
#: The board's servos by wire id.
SERVOS = {servo.wire_id: servo for servo in (ROLL, PITCH)}


# ---------------------------------------------------------------------------- units


def to_centideg(angle_rad: float) -> int:
    """Nearest whole centidegree of an angle in radians."""
    return round(math.degrees(angle_rad) * CENTIDEG_PER_DEG)


def from_centideg(centideg: int) -> float:
    """Radians of an angle in centidegrees."""
    return math.radians(centideg / CENTIDEG_PER_DEG)


def format_centideg(centideg: int) -> str:
    """Wire text of an angle: degrees with exactly two decimals, e.g. ``-11.45``."""
    sign = "-" if centideg < 0 else ""
    whole, frac = divmod(abs(int(centideg)), CENTIDEG_PER_DEG)
    return f"{sign}{whole}.{frac:02d}"


_ANGLE = re.compile(r"^(-?)(\d{1,5})(?:\.(\d{1,2}))?$")


def parse_centideg(text: str) -> int | None:
    """Centidegrees from wire text (``-11.45``, ``90``, ``90.5``), or None if malformed."""
    match = _ANGLE.match(text)
    if not match:
        return None
    sign, whole, frac = match.groups()
    value = int(whole) * CENTIDEG_PER_DEG + int((frac or "0").ljust(2, "0"))
    return -value if sign else value


def pulse_us(horn_centideg: int) -> int:
    """Pulse width (µs) for a horn angle, by the sketch's integer rounding."""
    lo_c, hi_c = HORN_RANGE_CENTIDEG
    lo_us, hi_us = PULSE_RANGE_US
    span = hi_c - lo_c
    return lo_us + ((horn_centideg - lo_c) * (hi_us - lo_us) + span // 2) // span


# ---------------------------------------------------------------------------- commands


def check_angle(servo: Servo, angle_rad: float) -> int:
    """The angle's wire centidegrees, after checking it against the servo's travel.

    Raises ``ValueError`` naming the servo and its travel (radians and degrees) for a
    non-finite angle or one outside the travel once rounded to the wire's centidegrees.
    """
    lo, hi = servo.travel_centideg
    try:
        value = float(angle_rad)
    except (TypeError, ValueError):
        value = math.nan
    if not math.isfinite(value) or not lo <= to_centideg(value) <= hi:
        raise ValueError(
            f"{servo.name} angle must be within [{servo.travel_rad[0]:.4f}, {servo.travel_rad[1]:.4f}] rad "
            f"([{format_centideg(lo)}, {format_centideg(hi)}] deg), got {angle_rad!r} rad")
    return to_centideg(value)


def hello() -> str:
    """Ask the board for its name and protocol version (``H``)."""
    return "H"


def set_angle(servo: Servo, angle_rad: float) -> str:
    """Move a servo (``S <id> <deg>``); ``ValueError`` if outside its travel (:func:`check_angle`)."""
    return f"S {servo.wire_id} {format_centideg(check_angle(servo, angle_rad))}"


def query(servo: Servo) -> str:
    """Ask for the angle last set on a servo (``? <id>``)."""
    return f"? {servo.wire_id}"


def calibrate(servo: Servo, offset_rad: float) -> str:
    """Set a servo's calibration offset (``C <id> <deg>``); horn angle = angle + offset."""
    try:
        value = float(offset_rad)
    except (TypeError, ValueError):
        value = math.nan
    if not math.isfinite(value) or abs(to_centideg(value)) > MAX_OFFSET_CENTIDEG:
        limit = MAX_OFFSET_CENTIDEG / CENTIDEG_PER_DEG
        raise ValueError(
            f"{servo.name} offset must be within +-{math.radians(limit):.4f} rad (+-{limit:g} deg), "
            f"got {offset_rad!r} rad")
    return f"C {servo.wire_id} {format_centideg(to_centideg(value))}"


# ---------------------------------------------------------------------------- framing


def frame(body: str) -> str:
    """``<body>*<checksum>`` (no line break); ``ValueError`` for a body the board would misread."""
    if not isinstance(body, str) or not body or not body.isascii() or any(c in body for c in "*\n\r"):
        raise ValueError(f"body must be non-empty ASCII without '*' or line breaks, got {body!r}")
    line = f"{body}*{checksum(body)}"
    if len(line) > MAX_LINE_BYTES:
        raise ValueError(f"body must frame to at most {MAX_LINE_BYTES} bytes, got {line!r}")
    return line


class Kind(enum.Enum):
    """What a line from the board means to the host."""

    OK = "ok"  # a command's answer; `words` echo the command
    ERR = "err"  # a refusal; `code` says why
    READY = "ready"  # boot banner
    CORRUPT = "corrupt"  # readable, but the checksum is missing or wrong
    GARBAGE = "garbage"  # undecodable bytes or control characters


@dataclass(frozen=True)
class Reply:
    """One classified line from the board."""

    kind: Kind
    text: str  # the line without its line break (repr of the bytes for GARBAGE)
    words: tuple[str, ...] = ()  # body words after OK / READY; after ERR's code, the message
    code: int | None = None  # ERR's code


_PRINTABLE = re.compile(r"^[\x20-\x7e]*$")


def unframe(text: str) -> str | None:
    """The body of ``<body>*<checksum>`` if the checksum holds, else None."""
    star = text.rfind("*")
    if star < 0 or not text[star + 1:].isdigit():
        return None
    body = text[:star]
    return body if int(text[star + 1:]) == checksum(body) else None


def parse_reply(raw: bytes) -> Reply:
    """Classify one line (with or without its line break) from the board."""
    try:
        text = raw.decode("ascii").rstrip("\r\n")
    except UnicodeDecodeError:
        return Reply(Kind.GARBAGE, repr(raw))
    if not _PRINTABLE.match(text):
        return Reply(Kind.GARBAGE, repr(raw))
    body = unframe(text)
    if body is None:
        return Reply(Kind.CORRUPT, text)
    words = tuple(body.split())
    if words[:1] == ("OK",):
        return Reply(Kind.OK, text, words[1:])
    if words[:1] == (BANNER_WORD,):
        return Reply(Kind.READY, text, words[1:])
    if words[:1] == ("ERR",) and len(words) >= 2 and words[1].isdigit():
        return Reply(Kind.ERR, text, (" ".join(words[2:]),), int(words[1]))
    return Reply(Kind.GARBAGE, text)


def answers(reply: Reply, body: str) -> bool:
    """Whether an ``OK`` reply answers the command ``body``: it echoes the command's
    letter and id, and for ``S``/``C`` its value."""
    if reply.kind is not Kind.OK:
        return False
    sent = body.split()
    if sent[0] == "?":
        return len(reply.words) == 3 and list(reply.words[:2]) == sent
    if sent[0] == "H":
        return reply.words[:1] == ("H",)
    return list(reply.words) == sent
