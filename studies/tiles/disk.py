"""The GelTip figure's tiles on disk: its columns, their files and their objects."""

from __future__ import annotations

import re
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from phong_reference.bake import METHODS
from scenes.errors import TactileSimError

#: The caption's objects, in the order of the figure's columns.
CAPTION = ("sphere", "cone", "indented_prism", "dots", "open_cylinder")
#: The published light fields, and the one whose tile the contact is recovered from.
FIELDS = METHODS
MATCH_FIELD = "linear"
#: The figure's column labels of the simulations' backgrounds.
BACKGROUNDS = ("nonebg", "solidbg", "realbg")
#: A tile's file name: the real sensor or a field, its column, its background label.
TILE_NAME = re.compile(r"^(?P<kind>real|" + "|".join(FIELDS) + r")_col(?P<column>\d+)_(?P<background>"
                       + "|".join(BACKGROUNDS) + r")\.png$")
#: A tile's height must be in this range, px, and its width over height in ASPECT_BOUNDS.
TILE_HEIGHT_BOUNDS_PX = (100, 400)
ASPECT_BOUNDS = (1.2, 1.5)


class TileError(TactileSimError, ValueError):
    """A tiles folder or tile that the study cannot use; the message names it."""


@dataclass(frozen=True)
class Column:
    """One column of the figure: its real tile and the published simulations of it.

    sims : field -> (path, background label), the MATCH_FIELD's always among them.
    """

    column: int
    real: Path
    sims: dict


def discover(folder: Path | str) -> dict[int, Column]:
    """The columns of a tiles folder, by file name (``TILE_NAME``), sorted.

    Raises TileError, naming the folder or file, for a folder that is missing or holds
    no real tile, a real tile without its MATCH_FIELD simulation, and a field given with
    two backgrounds; a simulation without its real tile is left out with a warning.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise TileError(f"tiles folder {folder} does not exist or is not a folder")
    found: dict[int, dict] = {}
    for path in sorted(folder.iterdir()):
        m = TILE_NAME.match(path.name)
        if m is None:
            continue
        k, kind, bg = int(m["column"]), m["kind"], m["background"]
        entry = found.setdefault(k, {})
        if kind in entry:
            raise TileError(f"tiles folder {folder}: column {k} has two {kind} tiles, {entry[kind][0].name} and "
                            f"{path.name}; keep one")
        entry[kind] = (path, bg)
    columns = {}
    for k, entry in sorted(found.items()):
        if "real" not in entry:
            names = ", ".join(p.name for p, _ in entry.values())
            warnings.warn(f"tiles folder {folder}: column {k} has simulations ({names}) but no real_col{k}_*.png; "
                          "left out", stacklevel=2)
            continue
        if MATCH_FIELD not in entry:
            raise TileError(f"real tile {entry['real'][0]} has no published {MATCH_FIELD} simulation beside it "
                            f"({MATCH_FIELD}_col{k}_{{{'|'.join(BACKGROUNDS)}}}.png), which its contact is "
                            "recovered from")
        sims = {f: entry[f] for f in FIELDS if f in entry}
        columns[k] = Column(k, entry["real"][0], sims)
    if not columns:
        raise TileError(f"tiles folder {folder} holds no real tiles (real_colK_{{{'|'.join(BACKGROUNDS)}}}.png)")
    return columns


def read_tile(path: Path | str) -> np.ndarray:
    """A tile, (h, w, 3) float64 in [0, 1]; TileError naming the file if it cannot be read or
    is not a 4:3 tile (height in TILE_HEIGHT_BOUNDS_PX, width / height in ASPECT_BOUNDS)."""
    from scenes.images import read_rgb

    try:
        tile = read_rgb(path).astype(np.float64)
    except (OSError, ValueError) as exc:
        raise TileError(f"tile {path} could not be read: {exc}") from None
    h, w = tile.shape[:2]
    lo, hi = TILE_HEIGHT_BOUNDS_PX
    if not (lo <= h <= hi and ASPECT_BOUNDS[0] <= w / h <= ASPECT_BOUNDS[1]):
        raise TileError(f"tile {path} must be a 4:3 tile of the 640x480 frame, {lo}-{hi} px high (the figure's are "
                        f"about 228x171), got {w}x{h} px")
    return tile


def object_of(column: int, objects: dict[int, str] | None = None) -> str:
    """A column's object: ``objects[column]`` when given, else the caption's (CAPTION)."""
    if objects and column in objects:
        return objects[column]
    if 0 <= column < len(CAPTION):
        return CAPTION[column]
    raise TileError(f"column {column} has no object in the caption (columns 0-{len(CAPTION) - 1}: "
                    f"{', '.join(CAPTION)}); name it with --object {column}=NAME")


def parse_objects(items) -> dict[int, str]:
    """``--object K=NAME`` items as {K: NAME}; TileError naming a bad one."""
    out = {}
    for item in items or ():
        k, sep, name = str(item).partition("=")
        if not sep or not k.strip().isdigit() or not name.strip():
            raise TileError(f"--object must be K=NAME (a column number and an indenter), got {item!r}")
        out[int(k)] = name.strip()
    return out
