"""On-disk cache of baked arrays, keyed by a hash of everything they depend on."""

from __future__ import annotations

import hashlib
import json
import os
import warnings
import zipfile
from pathlib import Path
from typing import Callable

import numpy as np

from .errors import TactileSimError
from .files import atomic_file

#: Environment variable that moves the cache (default ~/.cache/tactile-sim).
CACHE_ENV = "TACTILE_SIM_CACHE"


def cache_dir() -> Path:
    root = os.environ.get(CACHE_ENV) or os.path.join(os.path.expanduser("~"), ".cache", "tactile-sim")
    return Path(root)


def make_key(*parts) -> str:
    """Hash of JSON-able parts and numpy arrays, in order."""
    h = hashlib.sha256()
    for part in parts:
        if isinstance(part, np.ndarray):
            h.update(str(part.dtype).encode() + str(part.shape).encode())
            h.update(np.ascontiguousarray(part).tobytes())
        else:
            h.update(json.dumps(part, sort_keys=True, default=str).encode())
        h.update(b"|")
    return h.hexdigest()[:24]


def _checksum(arrays: dict[str, np.ndarray]) -> str:
    h = hashlib.sha256()
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(name.encode() + str(a.dtype).encode() + str(a.shape).encode() + a.tobytes())
    return h.hexdigest()


class CacheError(TactileSimError, ValueError):
    """A cache file is corrupt or belongs to another key."""


def read_entry(path: Path, key: str) -> dict[str, np.ndarray]:
    """Read a cache file and check its key and checksum; raises CacheError."""
    try:
        with open(path, "rb") as fh, np.load(fh, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError, KeyError) as exc:
        raise CacheError(f"cache file {path} is unreadable: {exc}") from None
    meta = arrays.pop("__meta__", None)
    if meta is None:
        raise CacheError(f"cache file {path} has no metadata")
    try:
        meta = json.loads(bytes(meta).decode())
    except (UnicodeDecodeError, json.JSONDecodeError):
        raise CacheError(f"cache file {path} has corrupt metadata") from None
    if meta.get("key") != key:
        raise CacheError(f"cache file {path} is stale: key {meta.get('key')} != {key}")
    if meta.get("checksum") != _checksum(arrays):
        raise CacheError(f"cache file {path} fails its checksum")
    return arrays


def write_entry(path: Path, key: str, arrays: dict[str, np.ndarray]) -> None:
    """Write atomically (``scenes.files.atomic_file``), streamed: entries reach 100 MB."""
    meta = json.dumps({"key": key, "checksum": _checksum(arrays)}).encode()
    with atomic_file(path) as fh:
        np.savez(fh, __meta__=np.frombuffer(meta, dtype=np.uint8), **arrays)


def cached(
    name: str, key: str, build: Callable[[], dict[str, np.ndarray]], *, use_cache: bool = True
) -> dict[str, np.ndarray]:
    """Return the arrays stored under (name, key), building and storing them if needed.

    A corrupt or stale file is reported with a warning and rebuilt.
    """
    if not use_cache:
        return build()
    path = cache_dir() / f"{name}-{key}.npz"
    if path.exists():
        try:
            return read_entry(path, key)
        except CacheError as exc:
            warnings.warn(f"{exc}; rebuilding", stacklevel=2)
    arrays = build()
    write_entry(path, key, arrays)
    return arrays
