"""Drive a Marlin printer over its serial host protocol (one command in flight at a time).

The text of the protocol lives in :mod:`rig.gcode`; this module is the transport and the
acknowledgement rules, over a pyserial port (a device path, a pty, or an open
``serial.Serial``-like object with ``read``, ``write``, ``flush``, ``in_waiting``,
``timeout`` and ``close``).

Rules implemented (Marlin ``Marlin/src/gcode/queue.cpp``):

* Connect: write one empty line (Marlin skips empty lines, so it is harmless; a twin uses it
  to learn that the host is there), wait up to ``banner_timeout_s`` for ``start`` and
  proceed without it (a board that does not reset on open never sends one), then send
  ``N0 M110 N0`` so the next line is N1, then ``G21`` and ``G90`` so that
  :meth:`MarlinPrinter.move_to` always means absolute millimetres.
* Every command is framed ``N<n> <command>*<checksum>`` and kept in a short history; the
  driver waits for ``ok`` (data lines before it are the command's reply).
* ``Resend: k`` (or ``rs k``): the firmware rejected line k; it follows with ``ok`` (which
  acknowledges the rejection, not a command), so the driver resends line k = n after that
  ``ok``, or after ``RESEND_OK_GRACE_S`` (or the reply timeout, if shorter) when the
  firmware sends none (some 2.0.x builds).
  ``Resend: n+1`` while waiting on line n means line n was already accepted: it is done.
  ``Resend: k`` with k < n asks for lines that were acknowledged (and run); the driver
  refuses rather than run moves twice, and so it does on a ``start`` after connecting.
  The preceding ``Error:checksum mismatch, Last Line: ..`` (or the line-number variant) is
  part of that sequence and not a failure.
* No reply within ``reply_timeout_s``: the same numbered line is written again, at most
  ``TIMEOUT_RETRIES`` times. Marlin executes line n only if the previous was n-1, so a line
  that did arrive is refused (and answered ``Resend: n+1``) rather than run twice. Then
  :class:`PrinterTimeout`.
* ``busy:``/``echo:busy:`` restarts the reply timeout; ``echo:`` is logged.
* Any other ``Error:`` raises :class:`PrinterError` (after the ``ok`` that may follow it).
* ``MAX_GARBAGE_LINES`` undecodable lines, or more than ``MAX_REPLY_LINES`` data lines,
  while waiting for one ``ok`` raise :class:`PrinterError` naming what came in.
* ``M112`` is written unnumbered and not acknowledged: Marlin accepts unnumbered lines and
  its emergency parser acts on them at once, and a line-number mismatch cannot block it.

The reply timeout must be longer than any command runs unless the firmware sends
``busy:`` (Marlin's ``HOST_KEEPALIVE_FEATURE``, on by default).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from typing import Self

import numpy as np

from rig import gcode
from rig.gcode import Kind
from rig.serial_lines import SerialLines, check_seconds
from scenes.errors import TactileSimError

log = logging.getLogger(__name__)

#: Marlin's usual USB baud rate (Anet A30 and most 32-bit boards).
DEFAULT_BAUD = 115200
#: Longest wait for ``ok`` with nothing (not even ``busy:``) from the firmware, seconds.
REPLY_TIMEOUT_S = 10.0
#: Wait for homing to finish, seconds.
HOME_TIMEOUT_S = 120.0
#: Wait for ``M400`` (all planned moves done), seconds.
MOVES_TIMEOUT_S = 120.0
#: Wait for the ``start`` banner after opening the port (boards reset on open), seconds.
BANNER_TIMEOUT_S = 3.0
#: After ``start``, the boot messages are drained until the line is quiet this long, seconds.
BANNER_QUIET_S = 0.1
#: Wait for the ``ok`` that follows ``Resend:`` (or the one after ``Error:``), seconds.
RESEND_OK_GRACE_S = 0.5
#: Longest blocking write, seconds.
WRITE_TIMEOUT_S = 2.0
#: Times a line is written again after a reply timeout before giving up.
TIMEOUT_RETRIES = 2
#: Resend requests tolerated while waiting for one ``ok``.
MAX_RESENDS = 10
#: Unreadable lines tolerated while waiting for one ``ok``.
MAX_GARBAGE_LINES = 3
#: Data lines tolerated while waiting for one ``ok`` (``M503`` prints about 50).
MAX_REPLY_LINES = 256
#: Sent lines kept for resending.
HISTORY_LINES = 64


class PrinterError(TactileSimError, RuntimeError):
    """The printer refused, reported a fault, or the port failed."""


class PrinterTimeout(PrinterError):
    """The printer did not answer in time."""


class MarlinPrinter:
    """A Marlin printer on a serial port.

    Parameters
    ----------
    port : str or serial.Serial-like
        Device path (``/dev/ttyUSB0``, a twin's pty) or an already-open port.
    baud : int
        Baud rate, used only when ``port`` is a path.
    reply_timeout_s : float, seconds
        Longest silence while waiting for ``ok``.
    banner_timeout_s : float, seconds
        Longest wait for the ``start`` banner on connect.
    """

    def __init__(self, port, baud: int = DEFAULT_BAUD, *, reply_timeout_s: float = REPLY_TIMEOUT_S,
                 banner_timeout_s: float = BANNER_TIMEOUT_S):
        check_seconds(reply_timeout_s=reply_timeout_s, banner_timeout_s=banner_timeout_s)
        self._link = SerialLines(port, baud, WRITE_TIMEOUT_S, "printer", PrinterError)
        self.port_name = self._link.name
        self.reply_timeout_s = float(reply_timeout_s)
        self._lock = threading.RLock()  # one command in flight
        self._write_lock = threading.Lock()  # also taken by the emergency stop
        self._history: OrderedDict[int, str] = OrderedDict()  # line number -> framed line
        self._next_line = 0  # number of the next framed line
        self._halted = False  # after M112 the firmware needs a reset
        self._connected = False  # line numbers agreed: a `start` now means the board rebooted
        try:
            self._wait_for_banner(float(banner_timeout_s))
            self._send(gcode.set_line_number(0))
            self._connected = True
            self.send(gcode.millimetre_units())
            self.send(gcode.absolute_positioning())
        except BaseException:
            self.close()
            raise

    # ------------------------------------------------------------------ commands

    def send(self, command: str, timeout_s: float | None = None) -> list[str]:
        """Send one command, framed, and wait for its ``ok``.

        ``M110`` is refused: the driver owns the line numbering.

        Returns
        -------
        list of str
            The data lines the firmware sent before ``ok`` (e.g. the ``M114`` position).
        """
        if isinstance(command, str) and command.strip().upper().startswith("M110"):
            raise ValueError(f"command must not be M110 (the driver numbers the lines), got {command!r}")
        return self._send(command, timeout_s)

    def _send(self, command: str, timeout_s: float | None = None) -> list[str]:
        timeout = self.reply_timeout_s if timeout_s is None else float(timeout_s)
        with self._lock:
            if self._halted:
                raise PrinterError(f"printer on {self.port_name} was halted by M112; reset it and reconnect")
            n = self._next_line
            line = gcode.frame(n, command)
            self._history[n] = line
            while len(self._history) > HISTORY_LINES:
                self._history.popitem(last=False)
            self._next_line = n + 1
            self._write(line)
            return self._await_ok(n, command, timeout)

    def home(self, timeout_s: float = HOME_TIMEOUT_S) -> None:
        """Home all axes (``G28``)."""
        self.send(gcode.home(), timeout_s)

    def move_to(self, xyz_m, feed_m_s: float) -> None:
        """Plan a linear move to ``xyz_m`` ((3,) metres) at ``feed_m_s`` (m/s).

        Returns once the firmware has queued it; call :meth:`wait_for_moves` to wait for it.
        """
        self.send(gcode.linear_move(xyz_m, feed_m_s))

    def wait_for_moves(self, timeout_s: float = MOVES_TIMEOUT_S) -> None:
        """Wait until every planned move has finished (``M400``)."""
        self.send(gcode.finish_moves(), timeout_s)

    def position(self) -> np.ndarray:
        """Current position ((3,) float64, metres) from ``M114``."""
        replies = self.send(gcode.report_position())
        for text in replies:
            if "X:" in text and "Y:" in text and "Z:" in text:
                return gcode.parse_position(text)
        raise PrinterError(f"M114 on {self.port_name} gave no position line, got {replies!r}")

    def quick_stop(self) -> None:
        """Stop all motion now, dropping planned moves (``M410``)."""
        self.send(gcode.quick_stop())

    def emergency_stop(self) -> None:
        """Kill the printer (``M112``), unnumbered and without waiting; it needs a reset after."""
        self._write(gcode.emergency_stop())
        self._halted = True

    def close(self) -> None:
        """Close the port if this object opened it. Safe to call twice."""
        self._link.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ protocol

    def _write(self, line: str) -> None:
        with self._write_lock:
            self._link.write(line)

    def _wait_for_banner(self, timeout_s: float) -> None:
        # Runs in __init__, before another thread can write (emergency_stop): no write lock.
        def is_start(raw: bytes) -> bool:
            reply = gcode.parse_reply(raw)
            log.debug("%s (banner) <- %s", self.port_name, reply.text)
            return reply.kind is Kind.START

        # the boot messages that follow 'start' are drained until the line goes quiet
        if not self._link.wait_for_banner(is_start, timeout_s, BANNER_QUIET_S):
            log.info("%s: no 'start' banner within %.1f s; assuming the firmware is running", self.port_name, timeout_s)

    def _await_ok(self, n: int, command: str, timeout_s: float) -> list[str]:
        """Read replies until the ``ok`` that completes line ``n``, following resends."""
        replies: list[str] = []  # data lines before ok
        garbage: list[str] = []  # repr of unreadable lines
        resends = 0
        retries = 0
        resend_from: int | None = None  # pending Resend request, acted on at the next ok
        error: str | None = None  # a real Error: seen; raised at the next ok
        grace_end = float("inf")  # when to act on a pending resend or error without an ok
        deadline = time.monotonic() + timeout_s
        where = f"{command!r} (line N{n}) on {self.port_name}"
        while True:
            raw = self._link.read_line(min(deadline, grace_end))
            now = time.monotonic()
            reply = None if raw is None else gcode.parse_reply(raw)
            if reply is not None:
                log.debug("%s <- %s", self.port_name, reply.text)
            if reply is None or reply.kind is Kind.OK:
                if reply is None and now < grace_end and now < deadline:
                    continue
                if error is not None:
                    raise PrinterError(f"printer error after {where}: {error}")
                if resend_from is not None:
                    first, resend_from, grace_end = resend_from, None, float("inf")
                    if first > n:  # line n had arrived before: nothing to send again
                        return replies
                    log.info("%s: resending %s", self.port_name, self._history[n])
                    self._write(self._history[n])
                    deadline = now + timeout_s
                    continue
                if reply is not None:
                    return replies
                if retries < TIMEOUT_RETRIES:
                    retries += 1
                    log.warning("%s: no reply to %s within %.2f s; writing it again", self.port_name, where, timeout_s)
                    self._write(self._history[n])
                    deadline = now + timeout_s
                    continue
                raise PrinterTimeout(
                    f"no 'ok' for {where} within {timeout_s:.2f} s, written {retries + 1} times")
            if reply.kind is Kind.RESEND:
                k = reply.number
                if command.startswith("M110"):
                    k = n  # the firmware's count was unknown until this line: resend it
                if k < n:
                    raise PrinterError(
                        f"{self.port_name} asked to resend line N{k}, already acknowledged, while waiting for "
                        f"{where}; not resending, so that no move runs twice (did the firmware restart?)")
                if k > n + 1:
                    raise PrinterError(
                        f"{self.port_name} asked to resend line N{k} while waiting for {where}; "
                        f"lines sent so far end at N{n}")
                resends += 1
                if resends > MAX_RESENDS:
                    raise PrinterError(f"{self.port_name} asked for more than {MAX_RESENDS} resends of {where}")
                resend_from, grace_end = k, now + RESEND_OK_GRACE_S
            elif reply.kind is Kind.LINE_ERROR:
                log.info("%s: %s (a Resend follows)", self.port_name, reply.text)
            elif reply.kind is Kind.ERROR:
                error, grace_end = reply.text, now + RESEND_OK_GRACE_S
            elif reply.kind is Kind.BUSY:
                deadline = now + timeout_s
            elif reply.kind is Kind.START and self._connected:
                raise PrinterError(
                    f"{self.port_name} restarted (sent 'start') while waiting for {where}; "
                    "its line numbers and position are lost: reconnect and home")
            elif reply.kind in (Kind.ECHO, Kind.START):
                log.info("%s: %s", self.port_name, reply.text)
            elif reply.kind is Kind.GARBAGE:
                garbage.append(reply.text)
                if len(garbage) >= MAX_GARBAGE_LINES:
                    raise PrinterError(
                        f"{self.port_name} sent {len(garbage)} unreadable lines while waiting for {where}: "
                        f"{', '.join(garbage)} (wrong baud rate, or a noisy cable?)")
            else:
                replies.append(reply.text)
                if len(replies) > MAX_REPLY_LINES:
                    raise PrinterError(
                        f"{self.port_name} sent more than {MAX_REPLY_LINES} lines without 'ok' while waiting "
                        f"for {where}; the last were {replies[-3:]!r}")
