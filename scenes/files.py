"""Files written whole or not at all: a temporary file in the same folder, then a rename.

A reader never sees half a file, and a run killed mid-write leaves only a hidden
``.NAME.*.tmp`` beside it, which a resumed dataset run removes (``scenes.dataset``).
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from pathlib import Path

import numpy as np


@contextlib.contextmanager
def atomic_file(path: str | Path):
    """A binary file handle whose contents become ``path`` when the block ends without an
    error (the folder made if missing); on any error the temporary file is removed and
    ``path`` is left as it was."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            yield fh
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def atomic_write_bytes(path: str | Path, data: bytes) -> None:
    """Write ``data`` to ``path`` whole or not at all (``atomic_file``)."""
    with atomic_file(path) as fh:
        fh.write(data)


def _json_default(value):
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    if isinstance(value, np.bool_):
        return bool(value)
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def write_json(path: str | Path, data: dict) -> None:
    """A study's JSON (a report, a benchmark's result), indented, numpy scalars and arrays
    as numbers and lists and NaN kept, written whole (``atomic_write_bytes``)."""
    atomic_write_bytes(path, (json.dumps(data, indent=2, default=_json_default, allow_nan=True) + "\n").encode())
