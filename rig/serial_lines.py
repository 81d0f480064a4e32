"""Lines over a serial port, shared by the rig's device drivers: opening a device with a
clear error, and splitting its bytes into lines, each read against a deadline."""

from __future__ import annotations

import time

try:
    import serial
except ImportError:  # the rig extra is not installed: the CLI still loads, opening a port says why
    serial = None

try:
    import termios

    _TERMIOS_ERRORS: tuple = (termios.error,)
except ImportError:  # not POSIX: pyserial raises no termios errors there
    _TERMIOS_ERRORS = ()

#: What a port raises when its device fails or goes away. pyserial's flush() on POSIX
#: calls termios.tcdrain, whose error is not an OSError: an unplugged cable raised a bare
#: "error: (5, 'Input/output error')" from a write, not the driver's error.
PORT_ERRORS = ((serial.SerialException,) if serial is not None else ()) + (OSError, *_TERMIOS_ERRORS)

#: One blocking read on the port, seconds; bounds how late a deadline is noticed.
READ_POLL_S = 0.02
#: A run of bytes this long without a line break is cut into a line of its own (garbage,
#: judged by the protocol's parser), so a noisy line cannot grow the buffer without bound.
MAX_LINE_BYTES = 512


class LineReader:
    """Split a serial port's bytes into lines, with a deadline per line."""

    def __init__(self, port):
        self._port = port
        self._buffer = bytearray()

    def read_line(self, deadline: float) -> bytes | None:
        """The next line (with its ``\\n``), or None once ``time.monotonic()`` passes deadline."""
        while True:
            end = self._buffer.find(b"\n")
            if end >= 0 or len(self._buffer) >= MAX_LINE_BYTES:
                cut = end + 1 if end >= 0 else MAX_LINE_BYTES
                line = bytes(self._buffer[:cut])
                del self._buffer[:cut]
                return line
            if time.monotonic() >= deadline:
                return None
            self._buffer += self._port.read(max(1, self._port.in_waiting))


def open_port(port: str, baud: int, write_timeout_s: float, device: str, error: type[Exception]):
    """Open ``port`` (a ``serial.Serial``) exclusively for reading lines; ``error`` (naming
    the ``device`` and the port) when it does not exist, another program holds it, or
    pyserial is not installed."""
    if serial is None:
        raise error(f"cannot open {device} port {port!r}: pyserial is not installed (pip install '.[rig]')")
    try:
        return serial.Serial(port, baud, timeout=READ_POLL_S, write_timeout=write_timeout_s, exclusive=True)
    except (serial.SerialException, OSError, ValueError) as exc:
        raise error(f"cannot open {device} port {port!r} at {baud} baud: {exc} "
                    "(does the device exist, and is no other program holding it?)") from exc


def check_seconds(**seconds: float) -> None:
    """``ValueError`` naming the first of the drivers' time arguments that is not >= 0 s."""
    for name, value in seconds.items():
        if not value >= 0:
            raise ValueError(f"{name} must be >= 0 seconds, got {value!r}")


class SerialLines:
    """A device's line link: its port (opened here from a path, or given open), lines
    written whole and lines read against a deadline, every port failure raised as the
    driver's ``error`` naming the port. Closes the port only if it opened it."""

    def __init__(self, port, baud: int, write_timeout_s: float, device: str, error: type[Exception]):
        self.error = error
        if isinstance(port, str):
            self.name = port
            self.serial = open_port(port, baud, write_timeout_s, device, error)
            self._owns = True
        else:
            self.name = getattr(port, "port", None) or repr(port)
            self.serial = port
            self._owns = False
            self.serial.timeout = READ_POLL_S
        self._reader = LineReader(self.serial)

    def write(self, line: str) -> None:
        """Write ``line`` and its line break."""
        try:
            self.serial.write((line + "\n").encode("ascii"))
            self.serial.flush()
        except PORT_ERRORS as exc:
            raise self.error(f"cannot write {line!r} to {self.name}: {exc}") from exc

    def read_line(self, deadline: float) -> bytes | None:
        """The next line, or None once ``time.monotonic()`` passes ``deadline``."""
        try:
            return self._reader.read_line(deadline)
        except PORT_ERRORS as exc:
            raise self.error(f"cannot read from {self.name}: {exc}") from exc

    def wait_for_banner(self, is_banner, timeout_s: float, quiet_s: float = 0.0) -> bool:
        """Wake the device (an empty line) and read until ``is_banner(raw line)`` says a line
        is its start-up banner, for at most ``timeout_s``; then, with ``quiet_s``, drain the
        boot lines that follow until the link stays quiet that long (within the same
        deadline). Whether the banner came."""
        self.write("")
        deadline = time.monotonic() + timeout_s
        while (raw := self.read_line(deadline)) is not None:
            if is_banner(raw):
                while quiet_s > 0 and self.read_line(min(deadline, time.monotonic() + quiet_s)) is not None:
                    pass
                return True
        return False

    def close(self) -> None:
        """Close the port if this link opened it. Safe to call twice."""
        if self._owns and self.serial is not None and self.serial.is_open:
            self.serial.close()
