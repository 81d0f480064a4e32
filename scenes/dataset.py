"""Tactile datasets on disk: one documented format for simulated, PBR and real captures.

See ``docs/dataset-format.md``. Every file is written atomically (a temporary file in the
same folder, then a rename), and ``samples.jsonl`` gets a sample's line only after its
image and depth files are complete, so an interrupted run resumes where it stopped with
nothing lost or duplicated.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import re
from pathlib import Path

import numpy as np

from .errors import TactileSimError
from .files import atomic_write_bytes
from .images import png_bytes, read_rgb, write_rgb

FORMAT = "tactile-sim-dataset"
VERSION = 1
SOURCES = ("sim", "pbr", "real")
#: Keys of dataset.json that must match when a run resumes into an existing folder.
IDENTITY_KEYS = ("format", "version", "source", "sensor", "protocol", "renderer")
#: Names an extra array may not take: they are record keys or folders of the format already.
RESERVED_ARRAY_NAMES = ("id", "image", "depth", "images")
ARRAY_NAME = re.compile(r"[a-z][a-z0-9_]*")


def atomic_write_json(path: Path, obj) -> None:
    atomic_write_bytes(path, (json.dumps(obj, indent=2, sort_keys=True) + "\n").encode())


def npy_bytes(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, array, allow_pickle=False)
    return buf.getvalue()


def sha256_json(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True).encode()).hexdigest()


def sample_id(index: int, obj: str) -> str:
    """File-system-safe id of a sample: its tap index, then its object (a mesh file's stem)."""
    if "/" in obj or "\\" in obj or Path(obj).suffix.lower() in (".stl", ".obj", ".ply", ".off", ".glb"):
        obj = Path(obj).stem
    safe = "".join(c if c.isalnum() or c in "-_" else "_" for c in obj)
    return f"{index:06d}_{safe}"


class DatasetError(TactileSimError, ValueError):
    """A dataset folder is corrupt, incomplete or of another kind than expected."""


class DatasetWriter:
    """Create or resume a dataset folder.

    Parameters
    ----------
    root : the folder.
    meta : the dataset.json content (``format`` and ``version`` are filled in). A folder
        that already holds a dataset must have the same identity (sensor, protocol,
        renderer, source) or the writer refuses it.
    protocol : the full protocol dict, written to ``protocol.json``.
    """

    def __init__(self, root: str | Path, meta: dict, protocol: dict | None = None):
        self.root = Path(root)
        meta = {"format": FORMAT, "version": VERSION, **meta}
        if meta.get("source") not in SOURCES:
            raise ValueError(f"dataset source must be one of {SOURCES}, got {meta.get('source')!r}")
        if protocol is not None:
            meta["protocol"] = {**meta.get("protocol", {}), "file": "protocol.json", "sha256": sha256_json(protocol)}
        self.meta = meta
        existing = self.root / "dataset.json"
        if existing.exists():
            old = read_meta(self.root)
            diff = [k for k in IDENTITY_KEYS if json.loads(json.dumps(old.get(k))) != json.loads(json.dumps(meta.get(k)))]
            if diff:
                raise DatasetError(
                    f"{self.root} already holds a dataset with different {', '.join(diff)}; "
                    "resume with the same settings or choose another folder"
                )
        else:
            (self.root / "images").mkdir(parents=True, exist_ok=True)
            (self.root / "depth").mkdir(parents=True, exist_ok=True)
            if protocol is not None:
                atomic_write_json(self.root / "protocol.json", protocol)
            atomic_write_json(existing, meta)
        self.done = {r["id"] for r in read_samples(self.root, repair=True)}
        # Temporary files of writes an interruption cut short; their samples are redone.
        for tmp in [*self.root.glob(".*.tmp"), *self.root.glob("*/.*.tmp")]:
            tmp.unlink(missing_ok=True)

    def append(self, record: dict) -> None:
        """Record a finished sample (its files must exist): one line, flushed to disk."""
        sid = record["id"]
        if sid in self.done:
            raise DatasetError(f"sample {sid} is already in {self.root / 'samples.jsonl'}")
        for key, value in record.items():
            is_file = key in ("image", "depth") or value == f"{key}/{sid}.npy"  # an extra array's file
            if is_file and value is not None and not (self.root / value).exists():
                raise DatasetError(f"sample {sid}: {value} was not written")
        line = json.dumps(record, sort_keys=True) + "\n"
        with open(self.root / "samples.jsonl", "a") as fh:
            fh.write(line)
            fh.flush()
            os.fsync(fh.fileno())
        self.done.add(record["id"])

    def write_background(self, image: np.ndarray) -> None:
        write_rgb(self.root / "background.png", image)


def check_array_name(name) -> str:
    """An extra array's name, checked: it names a folder and a record key."""
    if not isinstance(name, str) or not ARRAY_NAME.fullmatch(name) or name in RESERVED_ARRAY_NAMES:
        raise ValueError(f"array name must match {ARRAY_NAME.pattern} and not be one of {RESERVED_ARRAY_NAMES}, "
                         f"got {name!r}")
    return name


#: zlib level of a sample's PNG: bulk datasets favour speed (level 1 is several times
#: faster than the default 6, for files a tenth larger).
SAMPLE_PNG_LEVEL = 1


def sample_files(sid: str, image: np.ndarray, depth: np.ndarray | None,
                 arrays: dict[str, np.ndarray] | None = None) -> dict[str, tuple[str, bytes]]:
    """A sample's files, encoded and not written: record key -> (path relative to the
    dataset's root, bytes). Workers encode; the one process that appends to samples.jsonl
    writes them (:func:`write_files`).

    Parameters
    ----------
    image : (H, W, 3) float in [0, 1], as ``images/<sid>.png``.
    depth : (H, W) float, metres, as ``depth/<sid>.npy`` (float32), or None.
    arrays : extra arrays by name, each as ``<name>/<sid>.npy`` (float32).
    """
    arrays = {check_array_name(name): a for name, a in (arrays or {}).items()}
    files = {"image": (f"images/{sid}.png", png_bytes(image, compress_level=SAMPLE_PNG_LEVEL))}
    if depth is not None:
        files["depth"] = (f"depth/{sid}.npy", npy_bytes(np.asarray(depth, np.float32)))
    for name, array in arrays.items():
        files[name] = (f"{name}/{sid}.npy", npy_bytes(np.asarray(array, np.float32)))
    return files


def write_files(root: str | Path, files: dict[str, tuple[str, bytes]]) -> dict:
    """Write :func:`sample_files`' files atomically under root; returns their paths
    relative to root, by record key."""
    root = Path(root)
    for path, data in files.values():
        atomic_write_bytes(root / path, data)
    return {key: path for key, (path, _) in files.items()}


def write_sample_files(root: str | Path, sid: str, image: np.ndarray, depth: np.ndarray | None,
                       arrays: dict[str, np.ndarray] | None = None) -> dict:
    """Write a sample's files atomically (:func:`sample_files`); returns their paths
    relative to root, by record key. Only the process that appends to samples.jsonl
    calls it, after the files it returns."""
    return write_files(root, sample_files(sid, image, depth, arrays))


def read_meta(root: str | Path) -> dict:
    """dataset.json of a dataset folder, checked for format and version."""
    path = Path(root) / "dataset.json"
    if not path.exists():
        raise DatasetError(f"{root} is not a dataset: {path.name} is missing")
    try:
        meta = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DatasetError(f"{path} is corrupt: {exc}") from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise DatasetError(f"{path} is not a {FORMAT} file (format = {meta.get('format') if isinstance(meta, dict) else meta!r})")
    if meta.get("version") != VERSION:
        raise DatasetError(f"{path} has format version {meta.get('version')}, this reader knows {VERSION}")
    return meta


def read_samples(root: str | Path, repair: bool = False) -> list[dict]:
    """The sample records of a dataset, in the order they were written.

    A last line cut short by an interrupted write is dropped (and, with ``repair``, cut
    from the file); any other unreadable line is an error naming the line.
    """
    path = Path(root) / "samples.jsonl"
    if not path.exists():
        return []
    raw = path.read_bytes()
    lines = raw.split(b"\n")
    records, seen, good_end = [], set(), 0
    for number, line in enumerate(lines, start=1):
        if not line.strip():
            good_end += len(line) + 1
            continue
        last = number == len(lines)  # no newline after it: possibly cut short
        try:
            record = json.loads(line)
            if not isinstance(record, dict) or "id" not in record:
                raise ValueError("not a sample record with an 'id'")
        except ValueError as exc:
            if last:
                break
            raise DatasetError(f"{path}, line {number}: {exc}") from None
        if record["id"] in seen:
            raise DatasetError(f"{path}, line {number}: sample {record['id']} appears twice")
        seen.add(record["id"])
        records.append(record)
        good_end += len(line) + 1
    good_end = min(good_end, len(raw))
    if repair and good_end < len(raw):
        with open(path, "r+b") as fh:
            fh.truncate(good_end)
    return records


def load_sample(root: str | Path, record: dict, shape: tuple[int, int] | None = None):
    """(image (H, W, 3) float32, depth (H, W) float32 or None) of one sample record."""
    root = Path(root)
    image_path = root / record.get("image", "")
    if not image_path.is_file():
        raise DatasetError(f"{root}: sample {record.get('id')}: image {record.get('image')} is missing")
    try:
        image = read_rgb(image_path, shape)
    except ValueError as exc:
        raise DatasetError(f"{root}: sample {record.get('id')}: {exc}") from None
    depth = None
    if record.get("depth"):
        try:
            depth = np.load(root / record["depth"], allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise DatasetError(f"{root}: sample {record.get('id')}: depth {record['depth']} unreadable: {exc}") from None
    return image, depth
