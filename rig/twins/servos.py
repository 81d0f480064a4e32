"""A servo-board twin on a pseudo-terminal, with fault injection.

It answers :mod:`rig.servo_protocol` as ``rig/firmware/servo_rig/servo_rig.ino`` does: the
same checks in the same order (line length, checksum, syntax, servo id, travel, horn pulse
range, offset limit), the same error codes, the same integer centidegree arithmetic, and
offsets starting at the sketch's constants (:data:`DEFAULT_OFFSETS_CENTIDEG`, which a test
compares with the sketch). Like :mod:`rig.twins.printer`, it serves the master side of an
``os.openpty`` (slave in raw mode) from a background thread, and sends its banner when the
host first writes, since a pty cannot tell it when the port is opened.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass

from rig import servo_protocol as sp
from rig.servo_protocol import Code
from rig.twins.pty import GARBAGE, PtyTwin

log = logging.getLogger(__name__)

#: Offsets at boot, centidegrees, by wire id (the sketch's ROLL_OFFSET_CD, PITCH_OFFSET_CD).
DEFAULT_OFFSETS_CENTIDEG = {"R": 0, "P": 0}


@dataclass(frozen=True)
class ServoFaults:
    """Faults to inject, by arrival number: 0 is the first non-empty line the twin
    receives (the driver's ``H``), and every line written again gets a new number. After
    connecting, ``set_angles`` writes roll at 1 and pitch at 2."""

    drop: frozenset[int] = frozenset()  # line never reaches the board: no answer
    corrupt_commands: frozenset[int] = frozenset()  # line arrives damaged: ERR 1, not run
    corrupt_replies: frozenset[int] = frozenset()  # line runs; its answer's checksum is damaged
    error_at: int | None = None  # answered `ERR <error_code> <error_text>`, not run
    error_code: int = Code.PULSE
    error_text: str = "servo fault"
    garbage_at: int | None = None  # answered with GARBAGE, not run
    silent_from: int | None = None  # from this line on, no answer to anything

    def __post_init__(self):
        if int(self.error_code) in sp.TRANSMISSION_ERRORS:
            raise ValueError(f"error_code must not be a transmission error (those are resent), got {self.error_code}")


class ServoTwin(PtyTwin):
    """The servo board on a pty; see the module docstring.

    Parameters
    ----------
    faults : ServoFaults, optional
        Faults to inject; none by default.
    on_angles : callable, optional
        Called from the serving thread as ``on_angles(roll_rad, pitch_rad)`` after every
        accepted ``S`` once both servos have been set, e.g. to move the MuJoCo rig.
    """

    def __init__(self, faults: ServoFaults | None = None,
                 on_angles: Callable[[float, float], None] | None = None):
        self.faults = ServoFaults() if faults is None else faults
        self.on_angles = on_angles
        super().__init__("ServoTwin")
        self._received: list[str] = []  # every non-empty line, as it arrived
        self._commands: list[str] = []  # every body run (checksum good), in order
        self._offsets = dict(DEFAULT_OFFSETS_CENTIDEG)  # centidegrees, by wire id
        self._angles: dict[str, int | None] = {k: None for k in sp.SERVOS}  # last set, centidegrees
        self._pulses: dict[str, int | None] = {k: None for k in sp.SERVOS}  # pulse width driven, µs
        self._rx = bytearray()  # received bytes not yet split into lines
        self._overflow = False  # the current line outgrew the buffer
        self._silent = False
        self._start()

    # ------------------------------------------------------------------ records

    @property
    def received(self) -> list[str]:
        """Every non-empty line that arrived (dropped and damaged ones too), in order."""
        with self._lock:
            return list(self._received)

    @property
    def commands(self) -> list[str]:
        """Every command body the board ran, in order (a copy)."""
        with self._lock:
            return list(self._commands)

    @property
    def offsets_rad(self) -> dict[str, float]:
        """Calibration offsets by joint name, radians."""
        with self._lock:
            return {sp.SERVOS[k].name: sp.from_centideg(v) for k, v in self._offsets.items()}

    @property
    def horn_rad(self) -> dict[str, float | None]:
        """Horn angle (angle + offset) each servo is driven to, by joint name, radians; None if unset."""
        with self._lock:
            return {sp.SERVOS[k].name: None if a is None else sp.from_centideg(a + self._offsets[k])
                    for k, a in self._angles.items()}

    @property
    def pulses_us(self) -> dict[str, int | None]:
        """Pulse width each servo is driven with, by joint name, microseconds; None if unset."""
        with self._lock:
            return {sp.SERVOS[k].name: v for k, v in self._pulses.items()}

    # ------------------------------------------------------------------ serving

    def _banner(self) -> None:
        self._say(f"{sp.BANNER_WORD} {sp.FIRMWARE} {sp.PROTOCOL_VERSION}")

    def _feed(self, data: bytes) -> None:
        for byte in data:  # byte by byte, like the sketch's loop()
            self._receive(byte)

    def _receive(self, byte: int) -> None:
        if byte not in b"\r\n":
            if len(self._rx) < sp.MAX_LINE_BYTES:
                self._rx.append(byte)
            else:
                self._overflow = True
            return
        raw, overflow = bytes(self._rx), self._overflow
        self._rx.clear()
        self._overflow = False
        if not raw and not overflow:
            return
        try:
            self._handle(raw, overflow)
        except Exception as exc:  # tell the host rather than go silent
            log.exception("twin failed on %r", raw)
            self._say(f"ERR {Code.SYNTAX} twin failed: {exc}")

    def _say(self, body: str, corrupt: bool = False) -> None:
        line = f"{body}*{sp.checksum(body)}"  # not sp.frame: answers may outgrow the board's RX buffer
        if corrupt:  # flip the checksum's last digit
            line = line[:-1] + str((int(line[-1]) + 1) % 10)
        self._write((line + "\n").encode("ascii"))

    def _handle(self, raw: bytes, overflow: bool) -> None:
        text = raw.decode("ascii", errors="replace")
        with self._lock:
            k = len(self._received)
            self._received.append(text)
        faults = self.faults
        if faults.silent_from is not None and k >= faults.silent_from:
            self._silent = True
        if self._silent or k in faults.drop:
            return
        if overflow:
            self._say(f"ERR {Code.OVERFLOW} line longer than {sp.MAX_LINE_BYTES} bytes")
            return
        body = sp.unframe(text)
        if body is None or k in faults.corrupt_commands:
            self._say(f"ERR {Code.CHECKSUM} bad checksum")
            return
        if k == faults.error_at:
            self._say(f"ERR {int(faults.error_code)} {faults.error_text}")
            return
        if k == faults.garbage_at:
            self._write(GARBAGE)
            return
        with self._lock:
            self._commands.append(body)
        self._say(self._execute(body), corrupt=k in faults.corrupt_replies)

    def _execute(self, body: str) -> str:
        """Run one checked command as the sketch does; return the answer's body."""
        words = body.split(" ")
        letter, args = words[0], words[1:]
        if letter == "H" and not args:
            return f"OK H {sp.FIRMWARE} {sp.PROTOCOL_VERSION}"
        if letter not in ("S", "?", "C") or len(args) != (1 if letter == "?" else 2):
            return f"ERR {Code.SYNTAX} bad command"
        wire_id = args[0]
        if wire_id not in sp.SERVOS:
            return f"ERR {Code.SERVO} no servo {wire_id}"
        if letter == "?":
            angle = self._angles[wire_id]
            if angle is None:
                return f"ERR {Code.UNSET} {wire_id} not set"
            return f"OK ? {wire_id} {sp.format_centideg(angle)}"
        value = sp.parse_centideg(args[1])
        if value is None:
            return f"ERR {Code.SYNTAX} bad number"
        if letter == "C":
            if abs(value) > sp.MAX_OFFSET_CENTIDEG:
                return f"ERR {Code.OFFSET} {wire_id} offset beyond {sp.format_centideg(sp.MAX_OFFSET_CENTIDEG)}"
            with self._lock:
                self._offsets[wire_id] = value
            return f"OK C {wire_id} {sp.format_centideg(value)}"
        lo, hi = sp.SERVOS[wire_id].travel_centideg
        if not lo <= value <= hi:
            return f"ERR {Code.TRAVEL} {wire_id} outside {sp.format_centideg(lo)}..{sp.format_centideg(hi)}"
        horn = value + self._offsets[wire_id]
        horn_lo, horn_hi = sp.HORN_RANGE_CENTIDEG
        if not horn_lo <= horn <= horn_hi:
            return f"ERR {Code.PULSE} {wire_id} horn {sp.format_centideg(horn)} outside pulse range"
        with self._lock:
            self._angles[wire_id] = value
            self._pulses[wire_id] = sp.pulse_us(horn)
            both = None not in self._angles.values()
            roll, pitch = self._angles["R"], self._angles["P"]
        if both and self.on_angles is not None:
            self.on_angles(sp.from_centideg(roll), sp.from_centideg(pitch))
        return f"OK S {wire_id} {sp.format_centideg(value)}"
