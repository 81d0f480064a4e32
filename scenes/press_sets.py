"""Sets of real presses on disk, read as an ``Archive`` (the no-contact frame and each
press's frame as linear RGB in [0, 1], its annotated centre and radius in pixels) and
written as a folder: ``scenes.imports`` makes a capture dataset of one.

A format is one small reader (:data:`FORMATS`): a function from the archive's path to an
:class:`Archive`; the import is the same for every format (``scenes.imports.import_capture``).

The Taxim format (``taxim``, :func:`read_taxim`) is the calibration data pack of the
Taxim simulator (Si and Yuan, RA-L 2022; Robo-Touch/Taxim, ``calibs/dataPack*.npz``): an
``.npz`` (or a folder holding exactly one ``dataPack*.npz``) with ``f0`` (H, W, 3) uint8,
the no-contact frame; ``imgs`` (N, H, W, 3) uint8, one frame per press; ``touch_center``
(N, 2), each press's annotated centre in pixels as (x = column, y = row); ``touch_radius``
(N,), its annotated radius in pixels; and optionally ``names`` (N,). The frames are stored
as OpenCV reads them, BGR: the reader turns them to RGB.

A folder of presses (``folder``, :func:`read_folder`) is images and a table of each
press's image, centre and radius (``docs/dataset-format.md``); a set's records beside it
(``set.toml``, :func:`read_set_records`) state what the command line would.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


#: Defaults of each format: the sensor spec, the ball's diameter (metres) and the pixel's
#: size on the membrane (metres) of the set the format was published with.
TAXIM = "taxim"
DEFAULTS = {TAXIM: {"spec": Path(__file__).with_name("sensors") / "gelsight.toml", "ball_m": 4.0e-3,
                    "pixel_m": 0.1245e-3}}
@dataclass(frozen=True)
class Archive:
    """A published capture as a format reader returns it.

    no_contact : (H, W, 3) float64, linear RGB in [0, 1], the frame without contact.
    frames : (N, H, W, 3) float64, likewise, one per press.
    centres_px : (N, 2) float64, each press's annotated centre (u = column, v = row), px.
    radii_px : (N,) float64, each press's annotated radius, px.
    names : (N,) the presses' names in the archive.
    path : where it was read from.
    notes : what the reader did (e.g. the channel order it turned).
    depths_m : (N,) float64 or None, each press's depth where the archive records it
        (NaN where it does not), metres.
    balls_m : (N,) float64 or None, each press's ball diameter where the archive records
        it (NaN where it does not), metres.
    sha256 : a digest of what was read (default: of the file at ``path``).
    """

    no_contact: np.ndarray
    frames: np.ndarray
    centres_px: np.ndarray
    radii_px: np.ndarray
    names: tuple[str, ...]
    path: str
    notes: dict = field(default_factory=dict)
    depths_m: np.ndarray | None = None
    balls_m: np.ndarray | None = None
    sha256: str | None = None


def _npz_file(path: Path, pattern: str) -> Path:
    if path.is_dir():
        found = sorted(path.glob(pattern))
        if len(found) != 1:
            raise ValueError(f"archive {path}: a folder must hold exactly one {pattern}, found "
                             f"{[p.name for p in found] or 'none'}")
        return found[0]
    if not path.is_file():
        raise FileNotFoundError(f"archive {path} does not exist")
    return path


def read_taxim(path: str | Path) -> Archive:
    """Read a Taxim calibration data pack (module doc); ValueError naming the archive and
    the key for anything missing or malformed."""
    path = _npz_file(Path(path), "dataPack*.npz")
    try:
        pack = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise ValueError(f"archive {path} is not a readable .npz: {exc}") from None
    where = f"archive {path}"
    keys = set(pack.files)
    if "f0" not in keys:
        raise ValueError(f"{where} has no no-contact frame (key 'f0'); a capture needs one")
    for key in ("imgs", "touch_center", "touch_radius"):
        if key not in keys:
            raise ValueError(f"{where} has no {key!r}; a Taxim data pack has f0, imgs, touch_center and touch_radius")

    def array(key):
        try:
            return pack[key]
        except ValueError as exc:  # an object array (pickled): frames of unequal size, or Python objects
            raise ValueError(f"{where}: {key} is not one regular array ({exc}); frames of unequal size or Python "
                             "objects are not read") from None

    f0, imgs = array("f0"), array("imgs")
    for key, value, rank in (("f0", f0, 3), ("imgs", imgs, 4)):
        if value.dtype != np.uint8 or value.ndim != rank or value.shape[-1] != 3:
            want = "(H, W, 3)" if rank == 3 else "(N, H, W, 3)"
            raise ValueError(f"{where}: {key} must be {want} uint8 (8-bit BGR), got {value.shape} {value.dtype}")
    if imgs.shape[1:3] != f0.shape[:2]:
        raise ValueError(f"{where}: frames of unequal size: the presses are {imgs.shape[2]}x{imgs.shape[1]} px, the "
                         f"no-contact frame f0 {f0.shape[1]}x{f0.shape[0]} px")
    names = [str(n) for n in array("names")] if "names" in keys else [f"press_{i}" for i in range(len(imgs))]
    # Taxim's frames come from cv2.imread: BGR.
    return Archive(no_contact=f0[..., ::-1] / 255.0, frames=imgs[..., ::-1] / 255.0,
                   centres_px=np.asarray(array("touch_center"), np.float64),
                   radii_px=np.asarray(array("touch_radius"), np.float64), names=tuple(names[:len(imgs)]),
                   path=str(path.resolve()), notes={"channels": "stored BGR (OpenCV), turned to RGB"})


#: The folder format (``folder``, :func:`read_folder`): the press table's columns by role
#: (``--columns ROLE=NAME``), those it needs, the names its no-contact frame is looked for
#: under (any of IMAGE_SUFFIXES), and the file of a set's records beside an archive.
FOLDER = "folder"
COLUMNS = {"image": "image", "name": "name", "x": "x", "y": "y", "radius": "radius", "depth": "depth_mm",
           "ball": "ball_mm"}
REQUIRED_COLUMNS = ("image", "x", "y", "radius")
NO_CONTACT_NAMES = ("background", "no_contact", "nocontact", "f0", "ref", "reference")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
#: How a folder's images store their channels (stated, never guessed; RGB the default, as
#: PNG and JPEG files are written by every library but OpenCV).
CHANNELS = ("rgb", "bgr")
#: The quarter turns, clockwise in degrees, that frames and their annotations may be turned by.
TURNS = (0, 90, 180, 270)
#: What is done with printed marker dots on the membrane (``scenes.markers``).
MARKERS = ("keep", "inpaint")


def _read_8bit(path: Path, channels: str) -> np.ndarray:
    """An 8-bit colour image as (H, W, 3) uint8 in RGB order (``channels`` says how it is
    stored); ValueError naming the file for any other kind."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            mode = im.mode
            if mode not in ("RGB", "RGBA"):
                raise ValueError(f"image {path} is a {mode!r} image; an 8-bit colour (RGB) PNG or JPEG was expected")
            rgb = np.asarray(im.convert("RGB"), np.uint8)
    except OSError as exc:
        raise ValueError(f"image {path} could not be read as PNG or JPEG: {exc}") from None
    return rgb[..., ::-1] if channels == "bgr" else rgb


def _press_table(folder: Path, table: str | Path | None) -> Path:
    if table is not None:
        path = Path(table) if Path(table).is_absolute() else folder / table
        if not path.is_file():
            raise ValueError(f"folder {folder}: its press table {path} does not exist")
        return path
    found = sorted(p for p in folder.iterdir() if p.suffix.lower() in (".csv", ".json") and p.is_file())
    if len(found) != 1:
        raise ValueError(f"folder {folder} must hold one press table (a .csv or .json file), found "
                         f"{[p.name for p in found] or 'none'}; name it with --table FILE")
    return found[0]


def _table_rows(path: Path, columns: dict) -> list[dict]:
    """The table's rows as {role: value} (module doc of the folder format); ValueError
    naming the table, the row and the column for anything missing or not a number."""
    import csv

    where = f"press table {path}"
    try:
        if path.suffix.lower() == ".json":
            data = json.loads(path.read_text())
            rows = data.get("presses") if isinstance(data, dict) else data
            if not isinstance(rows, list) or not all(isinstance(r, dict) for r in rows):
                raise ValueError(f"{where}: a JSON table must be a list of objects, one per press, or "
                                 "{\"presses\": [...]}")
        else:
            with open(path, newline="", encoding="utf-8-sig") as fh:
                rows = list(csv.DictReader(fh))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, csv.Error) as exc:
        raise ValueError(f"{where} could not be read: {exc}") from None
    if not rows:
        raise ValueError(f"{where} holds no presses")
    have = set().union(*(r.keys() for r in rows))
    missing = [role for role in REQUIRED_COLUMNS if columns[role] not in have]
    if missing:
        what = ", ".join(f"{role} ({columns[role]!r})" for role in missing)
        raise ValueError(f"{where} has no column for {what}: each press needs its image, its centre (x = column, "
                         f"y = row, px) and radius (px); its columns are {sorted(have)}; name them with "
                         "--columns ROLE=NAME")
    out = []
    for i, row in enumerate(rows):
        got = {}
        for role, column in columns.items():
            value = row.get(column)
            if value is None or (isinstance(value, str) and not value.strip()):
                if role in REQUIRED_COLUMNS:
                    raise ValueError(f"{where}: row {i + 1} has no {role} (column {column!r})")
                got[role] = None
                continue
            if role in ("image", "name"):
                got[role] = str(value).strip()
                continue
            try:
                got[role] = float(value)
            except (TypeError, ValueError):
                raise ValueError(f"{where}: row {i + 1}, column {column!r}: {value!r} is not a number") from None
        out.append(got)
    return out


def _no_contact_path(folder: Path, name: str | None) -> Path:
    if name is not None:
        path = folder / name
        if not path.is_file():
            raise ValueError(f"folder {folder} has no no-contact frame {name!r}")
        return path
    found = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES
                   and p.stem.lower() in NO_CONTACT_NAMES)
    if len(found) != 1:
        names = ", ".join(f"{n}.png" for n in NO_CONTACT_NAMES)
        if not found:
            raise ValueError(f"folder {folder} has no no-contact frame (looked for {names} or .jpg); a capture needs "
                             "one: name it with --no-contact FILE")
        raise ValueError(f"folder {folder} has {len(found)} no-contact frames ({[p.name for p in found]}); name one "
                         "with --no-contact FILE")
    return found[0]


def read_folder(path: str | Path, table: str | Path | None = None, no_contact: str | None = None,
                columns: dict | None = None, channels: str = "rgb") -> Archive:
    """Read a folder of presses (module doc, ``docs/dataset-format.md``): its images named
    in a press table, and its no-contact frame. ValueError naming the folder, the table's
    row or the image for anything missing or malformed; nothing is written.

    table : the press table, a .csv or .json in the folder (default: its only one).
    no_contact : the no-contact frame's file name (default: the one named as NO_CONTACT_NAMES).
    columns : {role: column name} over COLUMNS' defaults.
    channels : how the images store their channels, "rgb" (default) or "bgr".
    """
    folder = Path(path)
    if not folder.is_dir():
        raise ValueError(f"folder {folder} does not exist or is not a folder (a folder of images, a no-contact frame "
                         "and a press table was expected)")
    if channels not in CHANNELS:
        raise ValueError(f"channels must be one of {CHANNELS}, got {channels!r}")
    unknown = sorted(set(columns or {}) - set(COLUMNS))
    if unknown:
        raise ValueError(f"--columns: unknown roles {unknown}; the roles are {sorted(COLUMNS)}")
    columns = {**COLUMNS, **(columns or {})}
    table_path = _press_table(folder, table)
    rows = _table_rows(table_path, columns)
    f0_path = _no_contact_path(folder, no_contact)
    digest = hashlib.sha256()
    for p in (table_path, f0_path):
        digest.update(p.name.encode() + b"\0" + p.read_bytes())
    f0 = _read_8bit(f0_path, channels)
    frames = np.empty((len(rows), *f0.shape), np.uint8)
    for i, row in enumerate(rows):
        name = f"folder {folder}: press {i} ({row['image']})"
        image = folder / row["image"]
        if image.resolve() == f0_path.resolve():
            raise ValueError(f"{name} names the no-contact frame {f0_path.name} as a press")
        if not image.is_file():
            raise ValueError(f"{name}: its image {image} is missing")
        frame = _read_8bit(image, channels)
        if frame.shape != f0.shape:
            raise ValueError(f"{name}: its image is {frame.shape[1]}x{frame.shape[0]} px, the no-contact frame "
                             f"{f0_path.name} {f0.shape[1]}x{f0.shape[0]} px; every frame must be the same size")
        frames[i] = frame
        digest.update(image.name.encode() + b"\0" + image.read_bytes())

    def column(role, scale=1.0):
        values = np.array([np.nan if r[role] is None else r[role] * scale for r in rows], np.float64)
        return None if np.isnan(values).all() else values

    return Archive(no_contact=f0 / 255.0, frames=frames / 255.0,
                   centres_px=np.array([[r["x"], r["y"]] for r in rows], np.float64),
                   radii_px=np.array([r["radius"] for r in rows], np.float64),
                   names=tuple(r["name"] or r["image"] for r in rows), path=str(folder.resolve()),
                   notes={"channels": f"stored {channels.upper()}" + (", turned to RGB" if channels == "bgr" else ""),
                          "table": table_path.name, "no_contact": f0_path.name},
                   depths_m=column("depth", 1e-3), balls_m=column("ball", 1e-3), sha256=digest.hexdigest())


def write_folder(archive: Archive, folder: str | Path, table: str = "presses.csv") -> Path:
    """Write ``archive`` as a folder of presses (:func:`read_folder` reads it back to the
    same frames, centres, radii and names): 8-bit RGB PNGs (lossless), ``background.png``,
    and a CSV table with the default columns. The folder must be new or empty."""
    import csv
    import io

    from .files import atomic_write_bytes
    from .images import png_bytes

    folder = Path(folder)
    if folder.exists() and any(folder.iterdir()):
        raise ValueError(f"folder {folder} is not empty; write a set of presses into a new folder")
    check_archive(archive)
    atomic_write_bytes(folder / "background.png", png_bytes(archive.no_contact))
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    roles = ["image", "name", "x", "y", "radius"] + [r for r, v in (("depth", archive.depths_m),
                                                                    ("ball", archive.balls_m)) if v is not None]
    writer.writerow([COLUMNS[r] for r in roles])
    for i, name in enumerate(archive.names):
        image = f"press_{i:04d}.png"
        atomic_write_bytes(folder / image, png_bytes(archive.frames[i]))
        row = [image, name, repr(float(archive.centres_px[i, 0])), repr(float(archive.centres_px[i, 1])),
               repr(float(archive.radii_px[i]))]
        for values in (archive.depths_m, archive.balls_m):
            if values is not None:
                row.append("" if np.isnan(values[i]) else repr(float(values[i]) * 1e3))
        writer.writerow(row)
    atomic_write_bytes(folder / table, buf.getvalue().encode())
    return folder


def turn_archive(archive: Archive, degrees: int) -> Archive:
    """``archive`` with its frames turned ``degrees`` (a multiple of 90) clockwise, and each
    press's annotated centre turned with them (radii, names and depths unchanged; its
    notes' ``turned_deg`` says by how much). Pixel
    centres lie on integers: a clockwise quarter turn of a W x H frame takes (u, v) to
    (H - 1 - v, u)."""
    if degrees not in TURNS:
        raise ValueError(f"a turn must be one of {TURNS} degrees clockwise, got {degrees!r}")
    k = degrees // 90
    if k == 0:
        return archive
    h, w = archive.no_contact.shape[:2]
    u, v = archive.centres_px[:, 0], archive.centres_px[:, 1]
    turned = {1: (h - 1 - v, u), 2: (w - 1 - u, h - 1 - v), 3: (v, w - 1 - u)}[k]
    return dataclasses.replace(
        archive, no_contact=np.rot90(archive.no_contact, -k, axes=(0, 1)).copy(),
        frames=np.rot90(archive.frames, -k, axes=(1, 2)).copy(), centres_px=np.stack(turned, axis=1),
        notes={**archive.notes, "turned_deg": degrees})


def orientation_turn(spec, width: int, height: int) -> int:
    """The quarter turn (0 or 90 degrees clockwise) that gives ``width`` x ``height`` frames
    the orientation (portrait or landscape) of the spec's camera."""
    c = spec.camera
    return 0 if (width >= height) == (c.width >= c.height) or width == height else 90


#: Keys a set's records (SET_RECORDS) may hold, and what each is.
SET_RECORDS = "set.toml"
SET_KEYS = {"format": "the archive's format (taxim, folder)", "spec": "a shipped sensor's name or a spec TOML's path",
            "ball_mm": "the ball's diameter, mm", "pixel_mm": "a pixel's size on the gel at the frames' size, mm",
            "channels": "rgb or bgr", "table": "the press table's file", "no_contact": "the no-contact frame's file",
            "columns": "a table of ROLE = column name", "turn": "0, 90, 180, 270 or auto",
            "markers": "keep or inpaint (printed marker dots)", "name": "the set's name", "notes": "free text"}


def set_records_path(archive: str | Path) -> Path | None:
    """Where a set's records sit beside ``archive``: ``set.toml`` in a folder, ``X.toml`` beside
    a file ``X.npz`` (or ``set.toml`` in its folder); None where there are none."""
    archive = Path(archive)
    for path in ([archive / SET_RECORDS] if archive.is_dir() else
                 [archive.with_suffix(".toml"), archive.parent / SET_RECORDS]):
        if path.is_file():
            return path
    return None


def read_set_records(archive: str | Path) -> dict:
    """The records of the set at ``archive`` (SET_KEYS), or {} where it has none; a spec
    given by a path is made absolute against the records' folder, a bare name is a shipped
    sensor (``scenes/sensors/<name>.toml``). ValueError naming the file and the key."""
    import tomllib

    path = set_records_path(archive)
    if path is None:
        return {}
    try:
        data = tomllib.loads(path.read_text())
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise ValueError(f"set records {path} could not be read: {exc}") from None
    unknown = sorted(set(data) - set(SET_KEYS))
    if unknown:
        raise ValueError(f"set records {path}: unknown keys {unknown}; the keys are "
                         + "; ".join(f"{k}: {v}" for k, v in SET_KEYS.items()))
    for key in ("ball_mm", "pixel_mm"):
        if key in data and not (isinstance(data[key], (int, float)) and not isinstance(data[key], bool)
                                and data[key] > 0):
            raise ValueError(f"set records {path}: {key} must be a positive number of millimetres, got {data[key]!r}")
    if "columns" in data and not (isinstance(data["columns"], dict)
                                  and all(isinstance(v, str) for v in data["columns"].values())):
        raise ValueError(f"set records {path}: columns must be a table of ROLE = \"column name\"")
    if "spec" in data:
        from .spec_read import spec_file

        data["spec"] = str(spec_file(data["spec"], path.parent))
    return {**data, "records": str(path)}


#: Format name -> reader.
FORMATS: dict[str, Callable[..., Archive]] = {TAXIM: read_taxim, FOLDER: read_folder}


def check_archive(archive: Archive) -> None:
    """Refuse an archive whose arrays disagree, or a press whose centre lies outside the
    frame or whose radius is not a positive number: ValueError naming the press."""
    where = f"archive {archive.path}"
    frames, f0 = np.asarray(archive.frames), np.asarray(archive.no_contact)
    if f0.ndim != 3 or f0.shape[-1] != 3:
        raise ValueError(f"{where}: the no-contact frame must be (H, W, 3), got {f0.shape}")
    if frames.ndim != 4 or frames.shape[1:] != f0.shape:
        raise ValueError(f"{where}: frames of unequal size: presses {frames.shape[1:]} against the no-contact "
                         f"frame's {f0.shape}")
    n = len(frames)
    if n == 0:
        raise ValueError(f"{where} holds no presses")
    centres, radii = np.asarray(archive.centres_px), np.asarray(archive.radii_px)
    if centres.shape != (n, 2) or radii.shape != (n,) or len(archive.names) != n:
        raise ValueError(f"{where}: {n} frames need {n} centres (N, 2), radii (N,) and names; got {centres.shape}, "
                         f"{radii.shape} and {len(archive.names)}")
    h, w = f0.shape[:2]
    for i, ((u, v), r) in enumerate(zip(centres, radii)):
        name = f"{where}: press {i} ({archive.names[i]})"
        if not (np.isfinite(u) and np.isfinite(v) and 0 <= u <= w - 1 and 0 <= v <= h - 1):
            raise ValueError(f"{name}: its centre ({u:g}, {v:g}) px lies outside the {w}x{h} frame "
                             "((x = column, y = row) in pixels was expected)")
        if not (np.isfinite(r) and r > 0):
            raise ValueError(f"{name}: its radius must be a positive number of pixels, got {r!r}")


def guess_format(archive: str | Path) -> str:
    """The format of ``archive`` when neither the command nor its records name one: a
    ``.npz``, or a folder holding one ``dataPack*.npz``, is Taxim's; any other folder is a
    folder of presses."""
    archive = Path(archive)
    if archive.suffix == ".npz" or (archive.is_dir() and len(list(archive.glob("dataPack*.npz"))) == 1):
        return TAXIM
    return FOLDER


#: The folder format's own options (a Taxim pack has none of them).
FOLDER_OPTIONS = ("table", "no_contact", "columns", "channels")
