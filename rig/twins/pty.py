"""A device twin on a real pseudo-terminal, which a driver opens like a USB serial port.

``os.openpty`` gives the pair; the slave (the port the host opens, ``port``) is put in
raw mode, and a background thread serves the master. A pty cannot tell when the host
opens its end, so the twin sends its boot banner when the host first writes (the
drivers write an empty line on connect, which the firmware skips). Subclasses say what
the banner is and what to do with the bytes that arrive.
"""

from __future__ import annotations

import os
import select
import threading
import time
import tty
from typing import Self

#: The serving thread's wait for bytes, seconds; bounds how late ``close`` is noticed.
POLL_S = 0.01
#: Longest wait for the serving thread on ``close``, seconds.
JOIN_TIMEOUT_S = 2.0
#: Unreadable bytes a twin's garbage fault sends, a few lines of them.
GARBAGE = b"\xff\xfe\x00\x9c\x81\xc3(\n" * 4


class PtyTwin:
    """The pty, its serving thread and its lifetime; subclasses implement ``_banner`` and
    ``_feed`` and call ``_start`` once their own state is set."""

    def __init__(self, name: str):
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        self.port = os.ttyname(self._slave)
        self._lock = threading.Lock()  # guards the records read by other threads
        self._banner_sent = False
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name=f"{name} {self.port}", daemon=True)

    def _start(self) -> None:
        self._thread.start()

    def close(self) -> None:
        """Stop the serving thread and close both ends of the pty. Safe to call twice."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(JOIN_TIMEOUT_S)
        for name in ("_master", "_slave"):
            fd = getattr(self, name)
            if fd is not None:
                os.close(fd)
                setattr(self, name, None)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def unplug(self) -> None:
        """Pull the cable: the pty's master closes, so the host's next read or write fails
        and the twin answers nothing more. Safe to call from the serving thread (e.g. in a
        callback, to unplug at an exact point of a session)."""
        self._stop.set()
        fd, self._master = self._master, None
        if fd is not None:
            os.close(fd)

    def _write(self, data: bytes) -> None:
        if self._master is not None:  # unplugged: the bytes go nowhere
            os.write(self._master, data)

    def _serve(self) -> None:
        while not self._stop.is_set() and (master := self._master) is not None:
            ready, _, _ = select.select([master], [], [], POLL_S)
            if not ready:
                continue
            try:
                data = os.read(master, 4096)
            except OSError:  # no slave open for a moment; try again
                time.sleep(POLL_S)
                continue
            if not self._banner_sent:
                self._banner_sent = True
                self._banner()
            self._feed(data)

    def _banner(self) -> None:
        raise NotImplementedError

    def _feed(self, data: bytes) -> None:
        raise NotImplementedError
