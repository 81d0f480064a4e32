"""Drive the rig's servo board (roll and pitch servos on an Arduino Mega) over pyserial.

The protocol (commands, framing, error codes, and why a checksum and no sequence number)
is documented in :mod:`rig.servo_protocol`; this module is the transport and the
acknowledgement rules, over a device path, a pty, or an open ``serial.Serial``-like object.

* Connect: write one empty line (the board ignores it; a twin uses it to learn that the
  host is there), wait up to ``banner_timeout_s`` for ``READY`` and go on without it (a board
  that does not reset on open sends none), then ``H``, whose answer must name
  ``servo_rig`` and this protocol's version.
* Angles are checked against the servos' travel *before* anything is written.
* One command in flight: the driver waits for the ``OK`` that echoes it. The same line is
  written again (every command is idempotent) on ``ERR 1``/``ERR 2`` or on a reply with a
  bad checksum, at most ``MAX_RESENDS`` times, and on silence for ``reply_timeout_s``, at
  most ``TIMEOUT_RETRIES`` times, then :class:`ServoTimeout` naming the command.
* An ``OK`` that echoes another command (a late answer to an earlier attempt) is skipped,
  at most ``MAX_STALE_REPLIES`` times. Any other ``ERR``, ``MAX_GARBAGE_LINES`` unreadable
  lines, or a ``READY`` after connecting (the board reset: offsets are back to the
  sketch's) raise :class:`ServoError`.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Self

from rig import servo_protocol as sp
from rig.serial_lines import SerialLines, check_seconds
from scenes.errors import TactileSimError

log = logging.getLogger(__name__)

#: The sketch's baud rate.
DEFAULT_BAUD = 115200
#: Longest wait for an answer, seconds (a command is parsed and answered in well under 1 ms;
#: the board answers before the servo has moved).
REPLY_TIMEOUT_S = 0.5
#: Wait for the banner after opening the port, seconds: the Mega's bootloader waits about
#: 1 s after the reset that opening the port causes, then the sketch starts.
BANNER_TIMEOUT_S = 3.0
#: Longest blocking write, seconds.
WRITE_TIMEOUT_S = 1.0
#: Times a line is written again after a reply timeout before giving up.
TIMEOUT_RETRIES = 2
#: Times a line is written again after a transmission error before giving up.
MAX_RESENDS = 5
#: Unreadable lines tolerated while waiting for one answer.
MAX_GARBAGE_LINES = 3
#: Answers to other commands tolerated while waiting for one answer.
MAX_STALE_REPLIES = 3


class ServoError(TactileSimError, RuntimeError):
    """The servo board refused a command, reported a fault, or the port failed."""


class ServoTimeout(ServoError):
    """The servo board did not answer in time."""


class ServoBoard:
    """The servo board on a serial port.

    Parameters
    ----------
    port : str or serial.Serial-like
        Device path (``/dev/ttyACM0``, a twin's pty) or an already-open port (not closed by
        :meth:`close`).
    baud : int
        Baud rate, used only when ``port`` is a path.
    reply_timeout_s : float, seconds
        Longest wait for one answer before the line is written again.
    banner_timeout_s : float, seconds
        Longest wait for the ``READY`` banner on connect.
    """

    def __init__(self, port, baud: int = DEFAULT_BAUD, *, reply_timeout_s: float = REPLY_TIMEOUT_S,
                 banner_timeout_s: float = BANNER_TIMEOUT_S):
        check_seconds(reply_timeout_s=reply_timeout_s, banner_timeout_s=banner_timeout_s)
        self._link = SerialLines(port, baud, WRITE_TIMEOUT_S, "servo board", ServoError)
        self.port_name = self._link.name
        self.reply_timeout_s = float(reply_timeout_s)
        self._lock = threading.Lock()  # one command in flight
        self._connected = False  # after H: a READY now means the board reset
        try:
            self._wait_for_banner(float(banner_timeout_s))
            reply = self._command(sp.hello())
            if list(reply.words[1:]) != [sp.FIRMWARE, str(sp.PROTOCOL_VERSION)]:
                raise ServoError(
                    f"{self.port_name} answered H with {reply.text!r}; expected "
                    f"'OK H {sp.FIRMWARE} {sp.PROTOCOL_VERSION}' (wrong device, or an old sketch?)")
            self._connected = True
        except BaseException:
            self.close()
            raise

    # ------------------------------------------------------------------ commands

    def set_angles(self, roll_rad: float, pitch_rad: float) -> None:
        """Move the sensor's roll servo and the indenter's pitch servo, radians.

        Both angles are checked against the servos' travel before anything is written
        (``ValueError`` naming the servo and its travel); returns once the board has
        acknowledged both (it does not wait for the servos to get there).
        """
        lines = [sp.set_angle(sp.ROLL, roll_rad), sp.set_angle(sp.PITCH, pitch_rad)]
        for line in lines:
            self._command(line)

    def angles(self) -> tuple[float, float]:
        """The angles last set on the board, ``(roll_rad, pitch_rad)``, to 0.01 degree."""
        values = []
        for servo in (sp.ROLL, sp.PITCH):
            reply = self._command(sp.query(servo))
            centideg = sp.parse_centideg(reply.words[2])
            if centideg is None:
                raise ServoError(f"{self.port_name} answered {sp.query(servo)!r} with {reply.text!r}, not an angle")
            values.append(sp.from_centideg(centideg))
        return values[0], values[1]

    def set_offset(self, servo: str, offset_rad: float) -> None:
        """Set a servo's calibration offset on the board (until it resets), radians.

        ``servo`` is ``"sensor_roll"`` or ``"indenter_pitch"``; the horn turns to angle +
        offset.
        """
        by_name = {s.name: s for s in sp.SERVOS.values()}
        if servo not in by_name:
            raise ValueError(f"servo must be one of {sorted(by_name)}, got {servo!r}")
        self._command(sp.calibrate(by_name[servo], offset_rad))

    def close(self) -> None:
        """Close the port if this object opened it. Safe to call twice."""
        self._link.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ protocol

    def _wait_for_banner(self, timeout_s: float) -> None:
        def is_ready(raw: bytes) -> bool:
            reply = sp.parse_reply(raw)
            log.debug("%s (banner) <- %s", self.port_name, reply.text)
            return reply.kind is sp.Kind.READY

        if not self._link.wait_for_banner(is_ready, timeout_s):
            log.info("%s: no %s banner within %.1f s; asking the board", self.port_name, sp.BANNER_WORD, timeout_s)

    def _command(self, body: str) -> sp.Reply:
        """Write one command and return the ``OK`` that answers it, following the rules above."""
        line = sp.frame(body)
        where = f"{body!r} on {self.port_name}"
        with self._lock:
            self._link.write(line)
            retries = resends = 0
            garbage: list[str] = []
            stale: list[str] = []
            deadline = time.monotonic() + self.reply_timeout_s
            while True:
                raw = self._link.read_line(deadline)
                if raw is None:
                    if retries >= TIMEOUT_RETRIES:
                        raise ServoTimeout(
                            f"no answer to {where} within {self.reply_timeout_s:.2f} s, written {retries + 1} times")
                    retries += 1
                    log.warning("%s: no answer to %s; writing it again", self.port_name, where)
                    self._link.write(line)
                    deadline = time.monotonic() + self.reply_timeout_s
                    continue
                reply = sp.parse_reply(raw)
                log.debug("%s <- %s", self.port_name, reply.text)
                if reply.kind is sp.Kind.OK and sp.answers(reply, body):
                    return reply
                damaged = reply.kind is sp.Kind.CORRUPT or (
                    reply.kind is sp.Kind.ERR and reply.code in sp.TRANSMISSION_ERRORS)
                if damaged:
                    resends += 1
                    if resends > MAX_RESENDS:
                        raise ServoError(
                            f"{where} was damaged in transit more than {MAX_RESENDS} times; last: "
                            f"{reply.text!r} (noisy cable, or wrong baud rate?)")
                    log.info("%s: %s; writing %s again", self.port_name, reply.text, line)
                    self._link.write(line)
                    deadline = time.monotonic() + self.reply_timeout_s
                elif reply.kind is sp.Kind.ERR:
                    try:
                        name = sp.Code(reply.code).name
                    except ValueError:
                        name = "unknown"
                    raise ServoError(f"board on {self.port_name} refused {body!r}: {reply.text} ({name})")
                elif reply.kind is sp.Kind.READY:
                    if self._connected:
                        raise ServoError(
                            f"{self.port_name} restarted (sent {reply.text!r}) while waiting for {where}; "
                            "its offsets are the sketch's again and the servos are released: reconnect")
                elif reply.kind is sp.Kind.OK:
                    stale.append(reply.text)
                    if len(stale) > MAX_STALE_REPLIES:
                        raise ServoError(f"{self.port_name} sent answers to other commands while waiting for {where}: "
                                         f"{stale!r}")
                else:
                    garbage.append(reply.text)
                    if len(garbage) >= MAX_GARBAGE_LINES:
                        raise ServoError(
                            f"{self.port_name} sent {len(garbage)} unreadable lines while waiting for {where}: "
                            f"{', '.join(garbage)} (wrong baud rate, or not the servo board?)")
