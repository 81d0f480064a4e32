"""Marlin's serial G-code protocol as pure functions over text: commands, framing, replies.

Everything here is SI (metres, m/s) in and G-code text out; G-code's millimetres and
mm/min exist only inside this module. Nothing here touches a port.

Protocol rules implemented (checked against Marlin's ``Marlin/src/gcode/queue.cpp``,
``GCodeQueue::get_serial_commands`` and ``gcode_line_error``/``flush_and_request_resend``,
and the message strings in ``Marlin/src/core/language.h``):

* A framed line is ``N<n> <command>*<checksum>``. The checksum is the XOR of every byte
  before the last ``*`` (leading spaces are skipped by the firmware, so :func:`frame` never
  writes any), as an unsigned 8-bit decimal number.
* The firmware strips ``;`` comments *before* checking the checksum, so a command with a
  ``;`` (or a ``*``, or a line break) cannot be framed and is refused.
* ``N<n>`` must be the last line number + 1, except on a line holding ``M110``, whose own
  ``N`` argument sets the number (``N0 M110 N0`` resets the count so the next line is N1).
* On a bad line the firmware answers ``Error:<reason>, Last Line: <last>``,
  ``Resend: <last + 1>`` and ``ok``; some 2.0.x builds, after the multi-serial rework of
  ``flush_and_request_resend``, leave that ``ok`` out (current 2.1.x sends it again).
  Reasons: ``checksum mismatch``, ``Line Number is not Last Line Number+1`` and ``No
  Checksum with line number``. These are the *line errors*; any other ``Error:`` is a real
  fault.
* ``busy: processing`` (sent as ``echo:busy: processing`` by the host keep-alive) means
  "still working"; ``echo:`` lines are informational; ``start`` is the boot banner;
  ``rs N`` is the old short form of ``Resend: N``.
"""

from __future__ import annotations

import enum
import math
import re
from dataclasses import dataclass

import numpy as np

#: Millimetres per metre (G-code lengths are millimetres, G21).
MM_PER_M = 1000.0
#: Seconds per minute (G-code feed rates are mm/min).
S_PER_MIN = 60.0
#: Decimals written for a coordinate in millimetres: 1 µm steps, finer than any FDM axis.
POSITION_DECIMALS = 3
#: Decimals written for a feed rate in mm/min.
FEED_DECIMALS = 1
#: Characters that cannot appear in a framed command: the firmware strips ``;`` comments
#: before checking the checksum, ``*`` starts the checksum, and a line break ends the line.
UNFRAMEABLE = (";", "*", "\n", "\r")
#: Marlin's reasons for rejecting a line, each followed by ``Resend:`` (language.h).
LINE_ERRORS = (
    "checksum mismatch",
    "Line Number is not Last Line Number+1",
    "No Checksum with line number",
)


# ---------------------------------------------------------------------------- commands


def home() -> str:
    """Home all axes (``G28``)."""
    return "G28"


def absolute_positioning() -> str:
    """Interpret coordinates as absolute (``G90``)."""
    return "G90"


def millimetre_units() -> str:
    """Lengths in millimetres (``G21``); every length this module writes assumes it."""
    return "G21"


def finish_moves() -> str:
    """Wait until every planned move has finished before answering ``ok`` (``M400``)."""
    return "M400"


def quick_stop() -> str:
    """Stop all steppers at once, dropping the planner queue (``M410``)."""
    return "M410"


def emergency_stop() -> str:
    """Kill the machine; it needs a reset afterwards (``M112``)."""
    return "M112"


def report_position() -> str:
    """Ask for the current position (``M114``); parse the answer with :func:`parse_position`."""
    return "M114"


def set_line_number(line_number: int = 0) -> str:
    """Set the firmware's last line number (``M110 N<n>``); the next line must be ``n + 1``."""
    _check_line_number(line_number, "line_number")
    return f"M110 N{line_number}"


def linear_move(xyz_m, feed_m_s: float) -> str:
    """Linear move to an absolute position (``G1 X.. Y.. Z.. F..``).

    Parameters
    ----------
    xyz_m : (3,) float, metres
        Target position in the printer's coordinates.
    feed_m_s : float, m/s
        Feed rate, > 0.

    Returns
    -------
    str
        e.g. ``G1 X10.000 Y20.000 Z5.000 F600.0`` (millimetres, mm/min).
    """
    xyz = np.asarray(xyz_m, dtype=float)
    if xyz.shape != (3,):
        raise ValueError(f"xyz_m must be (3,) metres, got shape {xyz.shape}")
    if not np.all(np.isfinite(xyz)):
        raise ValueError(f"xyz_m must be finite metres, got {xyz.tolist()}")
    feed = float(feed_m_s)
    if not math.isfinite(feed) or feed <= 0.0:
        raise ValueError(f"feed_m_s must be a finite speed > 0 m/s, got {feed_m_s!r}")
    x_mm, y_mm, z_mm = (xyz * MM_PER_M).tolist()
    feed_mm_per_min = feed * MM_PER_M * S_PER_MIN
    p, f = POSITION_DECIMALS, FEED_DECIMALS
    return f"G1 X{x_mm:.{p}f} Y{y_mm:.{p}f} Z{z_mm:.{p}f} F{feed_mm_per_min:.{f}f}"


# ---------------------------------------------------------------------------- framing


def checksum(text: str) -> int:
    """Marlin's line checksum: XOR of all bytes of ``text``, 0..255.

    Parameters
    ----------
    text : str
        ASCII, the line up to (not including) the ``*``, e.g. ``"N3 T0"``.
    """
    value = 0
    for byte in text.encode("ascii"):
        value ^= byte
    return value


def frame(line_number: int, command: str) -> str:
    """Marlin host-protocol line ``N<n> <command>*<checksum>`` (no line terminator).

    Raises ``ValueError`` for a negative line number, an empty or non-ASCII command, or one
    holding a character the firmware would treat specially (see ``UNFRAMEABLE``).
    """
    _check_line_number(line_number, "line_number")
    if not isinstance(command, str) or not command.strip():
        raise ValueError(f"command must be a non-empty G-code string, got {command!r}")
    if not command.isascii():
        raise ValueError(f"command must be ASCII, got {command!r}")
    bad = [c for c in UNFRAMEABLE if c in command]
    if bad:
        raise ValueError(f"command must not contain {bad!r} (comment, checksum or line break), got {command!r}")
    body = f"N{line_number} {command.strip()}"
    return f"{body}*{checksum(body)}"


def _check_line_number(line_number: int, name: str) -> None:
    if isinstance(line_number, bool) or not isinstance(line_number, (int, np.integer)) or line_number < 0:
        raise ValueError(f"{name} must be an integer >= 0, got {line_number!r}")


# ---------------------------------------------------------------------------- replies


class Kind(enum.Enum):
    """What a reply line from the firmware means to the host."""

    OK = "ok"  # the command finished (or, after a Resend, the rejected line is dealt with)
    RESEND = "resend"  # the firmware wants lines again from `number`
    LINE_ERROR = "line_error"  # a rejected line; a Resend follows
    ERROR = "error"  # a real fault
    BUSY = "busy"  # still processing: keep waiting
    ECHO = "echo"  # information, to be logged
    START = "start"  # boot banner
    DATA = "data"  # anything else printable, e.g. the M114 position line
    GARBAGE = "garbage"  # undecodable or control characters


@dataclass(frozen=True)
class Reply:
    """One classified reply line: its kind, its text and, for resends and line errors,
    the line number it carries (``Resend: N`` → N, ``Last Line: N`` → N)."""

    kind: Kind
    text: str
    number: int | None = None


_RESEND = re.compile(r"^(?:Resend|rs)\s*:?\s*N?(\d+)", re.IGNORECASE)
_LAST_LINE = re.compile(r"Last Line:\s*(-?\d+)")
_PRINTABLE = re.compile(r"^[\x20-\x7e\t]*$")


def parse_reply(raw: bytes) -> Reply:
    """Classify one reply line (without or with its ``\\n``) from Marlin.

    Bytes that are not ASCII, or hold control characters, are ``GARBAGE`` (the text is then
    their ``repr``); see :class:`Kind` for the rest.
    """
    try:
        text = raw.decode("ascii").strip("\r\n")
    except UnicodeDecodeError:
        return Reply(Kind.GARBAGE, repr(raw))
    if not _PRINTABLE.match(text):
        return Reply(Kind.GARBAGE, repr(raw))
    text = text.strip()
    if text == "ok" or text.startswith("ok "):
        return Reply(Kind.OK, text)
    match = _RESEND.match(text)
    if match:
        return Reply(Kind.RESEND, text, int(match.group(1)))
    if text.startswith("Error:"):
        body = text[len("Error:"):]
        if body.startswith(LINE_ERRORS):
            last = _LAST_LINE.search(body)
            return Reply(Kind.LINE_ERROR, text, int(last.group(1)) if last else None)
        return Reply(Kind.ERROR, text)
    if text.startswith(("busy:", "echo:busy:")):
        return Reply(Kind.BUSY, text)
    if text.startswith("echo:"):
        return Reply(Kind.ECHO, text)
    if text == "start":
        return Reply(Kind.START, text)
    return Reply(Kind.DATA, text)


_AXIS = re.compile(r"\b([XYZ]):\s*(-?\d+(?:\.\d*)?)")


def parse_position(reply: str) -> np.ndarray:
    """Position from an ``M114`` reply, e.g. ``X:10.00 Y:20.00 Z:5.00 E:0.00 Count X:800 ..``.

    Only the part before ``Count`` (the logical position in millimetres) is read; the
    stepper counts after it are ignored.

    Returns
    -------
    (3,) float64, metres
    """
    logical = reply.split("Count", 1)[0]
    found = {axis: float(value) for axis, value in _AXIS.findall(logical)}
    missing = [axis for axis in "XYZ" if axis not in found]
    if missing:
        raise ValueError(f"reply must be an M114 position line with X:, Y: and Z:, got {reply!r}")
    return np.array([found["X"], found["Y"], found["Z"]]) / MM_PER_M
