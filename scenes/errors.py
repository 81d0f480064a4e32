"""The project's error base class: what the command line reports in one line.

It lives in ``scenes`` because every other package depends on ``scenes`` and ``scenes``
on no other package, so each can derive its errors from it.
"""

from __future__ import annotations


class TactileSimError(Exception):
    """Base of every error that the project raises on purpose.

    These are failures a user can act on: a bad input file, a device that does not open
    or answer, a missing rendering platform, a session stopped on a fault. The command
    line (:func:`scenes.cli.main`) prints one as ``tactile-sim COMMAND: error: MESSAGE``
    and exits with status 1, without a traceback, so the message must stand on its own:
    name the input or device, what was expected and what came in.

    A subclass keeps a builtin base as well, so that callers may catch either: for
    example ``class PrinterError(TactileSimError, RuntimeError)`` for a device fault, or
    ``class DatasetError(TactileSimError, ValueError)`` for bad input.
    """


#: Errors that a command reports in one line (``tactile-sim COMMAND: error: ...``, exit
#: status 1) instead of a traceback: the project's own, bad input, and a file or device
#: that does not open (``OSError``, ``serial.SerialException`` among them). Library code
#: that goes on past such a failure (``studies.real_bench``) catches the same.
REPORTED = (TactileSimError, ValueError, OSError)
