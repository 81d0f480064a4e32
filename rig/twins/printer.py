"""A Marlin printer twin on a pseudo-terminal, with fault injection.

The twin opens a pty (``os.openpty``), puts its slave side in raw mode and serves the
master side from a background thread; a host opens :attr:`PrinterTwin.port` exactly like
``/dev/ttyUSB0``. It follows Marlin's ``GCodeQueue::get_serial_commands``
(``Marlin/src/gcode/queue.cpp``):

* a line ends at ``\\n`` or ``\\r``; empty lines are skipped; ``;`` starts a comment, which
  is removed before the checksum is checked; leading spaces are skipped;
* a line starting with ``N`` must carry the last line number + 1 (checked first; a line
  holding ``M110`` is exempt and its own ``N`` argument is used), then a ``*checksum``
  equal to the XOR of the bytes before the last ``*``;
* a bad line is answered ``Error:<reason>, Last Line: <last>``, the rest of the received
  bytes are discarded (Marlin empties its RX buffer), then ``Resend: <last + 1>`` and
  ``ok`` (Marlin 2.1.x; ``TwinFaults.ok_after_resend=False`` leaves the ``ok`` out, like
  some 2.0.x builds); an unnumbered line is accepted as is;
* ``M112`` answers ``Error:Printer halted. kill() called!`` and the twin ignores everything
  after it, like a killed board.

Commands run: G0/G1, G28, G90/G91, G21, M400, M114, M110, M410, M112. The position is kept
in millimetres, as firmware does; :attr:`PrinterTwin.moves` records every executed move.

A real board prints ``start`` when it boots, which happens as the host opens the port
(DTR reset). A pty cannot tell the twin when its slave is opened, so the twin sends its
banner when the first bytes from the host arrive, before handling them. The driver in
:mod:`rig.marlin` writes an empty line on connect for this reason (Marlin skips it).
"""

from __future__ import annotations

import logging
import re
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from rig import gcode
from rig.twins.pty import GARBAGE, PtyTwin

log = logging.getLogger(__name__)

#: Boot messages, the first being Marlin's banner.
BANNER = ("start", "echo:tactile-sim Marlin twin", "echo: Last Updated: twin")
#: Steps per millimetre reported by M114's ``Count`` (Anet A30 defaults: X, Y, Z).
STEPS_PER_MM = (80.0, 80.0, 400.0)
#: What M112 prints before the board stops (Marlin's MSG_ERR_KILLED).
KILLED = "Error:Printer halted. kill() called!"


@dataclass(frozen=True)
class TwinFaults:
    """Faults to inject, by the line number ``N`` of the host's framed lines.

    After connecting, :class:`rig.marlin.MarlinPrinter` has sent ``N0 M110 N0``, ``N1 G21``
    and ``N2 G90``; its next command is N3.
    """

    drop_lines: frozenset[int] = frozenset()  # first arrival never reaches the twin: no reply
    mute_lines: frozenset[int] = frozenset()  # first arrival runs but its `ok` is lost
    corrupt_lines: frozenset[int] = frozenset()  # first arrival fails its checksum
    corrupt_rate: float = 0.0  # probability that any numbered line fails its checksum
    seed: int = 0  # seed of the corrupt_rate draws
    error_at_line: int | None = None  # answered `Error:<error_text>` and `ok`, not run
    error_text: str = "MAXTEMP triggered"
    garbage_at_line: int | None = None  # answered with GARBAGE and no `ok`
    silent_from_line: int | None = None  # from this line on, no reply to anything
    forget_count_at_line: int | None = None  # the count resets to 0 just before this line
    restart_at_line: int | None = None  # the board reboots on this line: `start`, line count 0
    ok_after_resend: bool = True  # False: like some Marlin 2.0.x, no `ok` after `Resend:`
    busy_s: float = 0.0  # M400 sends `echo:busy: processing` this long before `ok`, seconds
    busy_interval_s: float = 0.05  # period of those busy lines, seconds

    def __post_init__(self):
        if not 0.0 <= self.corrupt_rate <= 1.0:
            raise ValueError(f"corrupt_rate must be a probability in [0, 1], got {self.corrupt_rate!r}")
        if not self.busy_s >= 0.0:
            raise ValueError(f"busy_s must be >= 0 seconds, got {self.busy_s!r}")
        if not self.busy_interval_s > 0.0:
            raise ValueError(f"busy_interval_s must be > 0 seconds, got {self.busy_interval_s!r}")


@dataclass(frozen=True)
class Move:
    """One executed G0/G1 (or G28, as a move to the origin)."""

    line_number: int | None  # N of the line that commanded it (None if unnumbered)
    command: str  # the command as run, without N and checksum
    position_m: np.ndarray  # (3,) float64, metres, after the move
    feed_m_s: float  # feed rate in force, m/s


_WORD = re.compile(r"([A-Z])\s*([-+]?\d*\.?\d*)")
_LEADING_INT = re.compile(r"[-+]?\d+")


class PrinterTwin(PtyTwin):
    """A Marlin printer on a pty; see the module docstring.

    Parameters
    ----------
    faults : TwinFaults, optional
        Faults to inject; none by default.
    on_move : callable, optional
        Called from the serving thread with the (3,) position in metres after each move
        or homing, e.g. to move a simulated rig.
    """

    def __init__(self, faults: TwinFaults | None = None, on_move: Callable[[np.ndarray], None] | None = None):
        faults = TwinFaults() if faults is None else faults
        self.faults = faults
        self.on_move = on_move
        self._rng = np.random.default_rng(faults.seed)
        super().__init__("PrinterTwin")
        self._moves: list[Move] = []  # every executed move
        self._lines: list[tuple[int | None, str]] = []  # every accepted line: (N, command)
        self._rejected: list[tuple[int, str]] = []  # every refused line: (N, reason)
        self._dropped: list[int] = []  # line numbers lost by the drop fault
        self._position_mm = np.zeros(3)  # X, Y, Z, millimetres, like firmware
        self._feed_mm_per_min = 1500.0  # feed rate in force
        self._absolute = True  # G90 / G91
        self._last_n = 0  # Marlin's last_N
        self._seen: set[int] = set()  # line numbers that have arrived once
        self._muted: set[int] = set()  # line numbers whose `ok` has been withheld once
        self._rx = bytearray()  # received bytes not yet split into lines
        self._silent = False  # the silent fault has started
        self.halted = False  # after M112
        self._start()

    # ------------------------------------------------------------------ records

    @property
    def moves(self) -> list[Move]:
        """Every executed move, in order (a copy)."""
        with self._lock:
            return list(self._moves)

    @property
    def lines(self) -> list[tuple[int | None, str]]:
        """Every accepted line as ``(N, command)``, in order (a copy)."""
        with self._lock:
            return list(self._lines)

    @property
    def rejected(self) -> list[tuple[int, str]]:
        """Every refused line as ``(N, reason)``, in order (a copy)."""
        with self._lock:
            return list(self._rejected)

    @property
    def dropped(self) -> list[int]:
        """Line numbers the drop fault swallowed, in order (a copy)."""
        with self._lock:
            return list(self._dropped)

    @property
    def position_m(self) -> np.ndarray:
        """Current position, (3,) float64, metres."""
        with self._lock:
            return self._position_mm / gcode.MM_PER_M

    # ------------------------------------------------------------------ serving

    def _banner(self) -> None:
        self._say(*BANNER)

    def _feed(self, data: bytes) -> None:
        self._rx += data
        while (end := _eol(self._rx)) >= 0:
            raw = bytes(self._rx[:end])
            del self._rx[: end + 1]
            try:
                self._handle(raw)
            except Exception as exc:  # tell the host rather than go silent
                log.exception("twin failed on %r", raw)
                self._say(f"Error:twin failed: {exc}", "ok")

    def _say(self, *lines: str) -> None:
        self._write("".join(line + "\n" for line in lines).encode("ascii"))

    def _line_error(self, n: int, reason: str) -> None:
        with self._lock:
            self._rejected.append((n, reason))
        del self._rx[:]  # Marlin empties its RX buffer before asking for the resend
        ok = ("ok",) if self.faults.ok_after_resend else ()
        self._say(f"Error:{reason}, Last Line: {self._last_n}", f"Resend: {self._last_n + 1}", *ok)

    def _handle(self, raw: bytes) -> None:
        if self.halted:
            return
        text = raw.decode("ascii", errors="replace").split(";", 1)[0]
        command = text.lstrip(" ")
        if command.strip().upper() == "M112":
            # Marlin's emergency parser acts on M112 as it arrives, even with the command
            # queue stuck or the replies lost.
            with self._lock:
                self._lines.append((None, "M112"))
            self.halted = True
            self._say(KILLED)
            return
        if self._silent:
            return
        if not command.strip():
            return
        n = None
        if command.startswith("N"):
            n_field = command
            is_m110 = "M110" in command
            if is_m110 and (second := command.find("N", 4)) >= 0:
                n_field = command[second:]
            match = _LEADING_INT.match(n_field, 1)
            n = int(match.group()) if match else 0
            faults, first_arrival = self.faults, n not in self._seen
            self._seen.add(n)
            if faults.silent_from_line is not None and n >= faults.silent_from_line:
                self._silent = True
                return
            if first_arrival and n == faults.forget_count_at_line:
                self._last_n = 0
            if n == faults.restart_at_line:
                self._last_n = 0
                self._say(*BANNER)
                return
            if first_arrival and n in faults.drop_lines:
                with self._lock:
                    self._dropped.append(n)
                return
            if n != self._last_n + 1 and not is_m110:
                self._line_error(n, gcode.LINE_ERRORS[1])
                return
            star = command.rfind("*")
            if star < 0:
                self._line_error(n, gcode.LINE_ERRORS[2])
                return
            corrupted = (first_arrival and n in faults.corrupt_lines) or (
                faults.corrupt_rate > 0.0 and self._rng.random() < faults.corrupt_rate)
            try:
                sent = int(command[star + 1:].strip())
            except ValueError:
                sent = -1
            if corrupted or sent != gcode.checksum(command[:star]):
                self._line_error(n, gcode.LINE_ERRORS[0])
                return
            self._last_n = n
            command = command[:star].split(" ", 1)[1] if " " in command[:star] else ""
            if n == faults.error_at_line:
                self._say(f"Error:{faults.error_text}", "ok")
                return
            if n == faults.garbage_at_line:
                self._write(GARBAGE)
                return
        command = command.strip()
        with self._lock:
            self._lines.append((n, command))
        reply = self._execute(n, command.upper())
        if n is not None and n in self.faults.mute_lines and n not in self._muted:
            self._muted.add(n)
            reply = [line for line in reply if line != "ok"]
        if reply:
            self._say(*reply)

    def _execute(self, n: int | None, command: str) -> list[str]:
        """Run one accepted command; return the lines to answer, ``ok`` last."""
        words = _WORD.findall(command)
        if not words:
            return ["ok"]
        code = words[0][0] + words[0][1]
        args = {letter: float(value) for letter, value in words[1:] if value not in ("", "-", "+", ".")}
        if code in ("G0", "G1", "G00", "G01"):
            with self._lock:
                for i, axis in enumerate("XYZ"):
                    if axis in args:
                        self._position_mm[i] = args[axis] if self._absolute else self._position_mm[i] + args[axis]
                if "F" in args:
                    self._feed_mm_per_min = args["F"]
                self._moves.append(Move(n, command, self._position_mm / gcode.MM_PER_M,
                                        self._feed_mm_per_min / gcode.MM_PER_M / gcode.S_PER_MIN))
            return self._moved()
        if code == "G28":
            with self._lock:
                axes = [i for i, axis in enumerate("XYZ") if axis in command[3:]] or [0, 1, 2]
                self._position_mm[axes] = 0.0
            return self._moved()
        if code in ("G90", "G91"):
            self._absolute = code == "G90"
            return ["ok"]
        if code in ("G21", "M410"):
            return ["ok"]
        if code == "M110":
            if "N" in args:
                self._last_n = int(args["N"])
            return ["ok"]
        if code == "M400":
            end = time.monotonic() + self.faults.busy_s
            while time.monotonic() < end and not self._stop.is_set():
                self._say("echo:busy: processing")
                self._stop.wait(self.faults.busy_interval_s)
            return ["ok"]
        if code == "M114":
            x, y, z = self._position_mm.tolist()
            counts = [round(p * s) for p, s in zip((x, y, z), STEPS_PER_MM, strict=True)]
            return [f"X:{x:.2f} Y:{y:.2f} Z:{z:.2f} E:0.00 Count X:{counts[0]} Y:{counts[1]} Z:{counts[2]}", "ok"]
        if code == "M112":
            self.halted = True
            return [KILLED]
        return [f'echo:Unknown command: "{command}"', "ok"]

    def _moved(self) -> list[str]:
        if self.on_move is not None:
            try:
                self.on_move(self.position_m)
            except Exception as exc:  # report to the host rather than kill the thread
                log.exception("on_move failed")
                return [f"Error:on_move failed: {exc}", "ok"]
        return ["ok"]


def _eol(buffer: bytearray) -> int:
    """Index of the first ``\\n`` or ``\\r`` (Marlin's ISEOL), or -1."""
    ends = [i for i in (buffer.find(b"\n"), buffer.find(b"\r")) if i >= 0]
    return min(ends) if ends else -1
