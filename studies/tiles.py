"""Recover the GelTip figure's contacts, and score both renderers on its real tiles.

Issue 52 item 4. The seed paper's figure shows, per column, a real GelTip tactile image
and the published fast model's simulation of the same contact with each of its four
light fields, all scaled down about 2.8 times (``real_contacts/README.md`` of the shared
data). The contacts' depth maps are not published; this study finds them back and
renders them with our reference and our fast path, against the real tile.

1. **Alignment.** A tile is a crop of the figure: tile pixel (row i, column j) is frame
   pixel (u, v) = (offset_u + scale j, offset_v + scale i) of the 640x480 frame
   (:class:`Alignment`). A frame image is brought to a tile by :func:`to_tile`: a
   Gaussian blur of sigma (scale - 1) / 2 frame px (scikit-image's anti-aliasing for
   a down-scale), then bilinear sampling. A tile's alignment is fitted
   (:func:`align`, Nelder-Mead, least mean |difference|) to a frame image of the same
   scene: the published tile to the published model's render, the real tile to the
   published real no-contact image (``real/bkg.png``), from the centred crop of the
   frame's height (scale H / h), the scale within SCALE_SLACK of that and the offsets
   within SHIFT_BOUND_PX frame px.
   The tiles are crops of a few px either way (measured: scale 2.82 on every tile that
   has a background, offsets -6 to +4 frame px); a centred resize instead leaves 3 to 8
   times the MAE on the linear tiles.
2. **The published model** (:class:`PaperModel`): their baked fields, prepared as
   ``studies.reproduce_published`` prepares them (blur, resize, rectification on the
   Sobel normals of their D_ref), with the paper dataset's settings (``NOTES.md``):
   Table 1's LEDs (the default spec's), i_a = 0.8, R.V not clamped, their D_ref
   (``sim_depth/bkg.npy``), and the tile's background: none (``nonebg``), the solid
   colour (``solidbg``) or the real no-contact image divided by 225 (``realbg``; the
   no-contact renders match the realbg tiles with 225, MAE 0.009-0.028, and not with
   255, 0.013-0.054), quantised to 8 bits as published (``to_8bit``).
3. **Recovery** (:func:`recover`), on the linear field's tile: the tap is the caption's
   object pressed by ``scenes.contact.press`` along the membrane's normal at the pixel
   (u, v) where the camera sees the contact point, ``depth`` deep, rolled by ``roll``
   about the normal (objects that are not round only). Their membrane mesh
   (``meshes/sensor/160x120_aligned_mesh.stl``, which ray-casts their D_ref to 0.008 mm
   median, ours to 0.038 mm) gives the point and normal. The search, on the tile's mean
   squared error over its pixels but a BORDER_PX frame (the figure's white gaps):

   * place: the centroid of the largest patch (by its sum of change; pixels
     PATCH_GAP_PX apart joined, so that an outline is one patch) where the tile differs
     from the model's no-contact render by more than CHANGE_LEVEL (mean over channels),
     inside the image circle less CIRCLE_MARGIN_PX (whose edge shows any crop error);
     then a coarse grid of COARSE_OFFSETS_PX (u and v) about it, and a refine within
     PLACE_BOUND_PX of it;
   * depth: COARSE_DEPTHS_MM, refined within DEPTH_BOUNDS_MM;
   * roll: COARSE_ROLLS steps over the object's symmetry period (ROLL_PERIOD_RAD, a
     full turn unless listed), refined within one step of the best;
   * the grid and a first bounded Nelder-Mead (``scipy.optimize``, REFINE_EVALUATIONS
     renders) on the tiles blurred by COARSE_BLUR_PX (thin outlines, such as the prism's
     in the linear tile, give a narrow basin otherwise), a second one on the sharp
     tiles; then the tile is aligned again to the recovered tap's render (the contact
     included) and the search refined once more (half the renders).

   How well it holds: per field, the MAE of the recovered tap's render against that
   field's tile (over the tile and over the contact, where the tile differs from the
   no-contact render by more than CHANGE_LEVEL, dilated by REGION_DILATION), beside the
   no-contact render's MAE; each field's tile is aligned to the recovered tap's render.
4. **Against the real tile** (:func:`score`): the recovered tap (pixel, depth, roll) is
   pressed on our membrane and rendered by the reference (``pbr``, default effects,
   ``--photons``) and by our fast path (``phong``, its default field), each with its
   own no-contact frame, both brought to the real tile by its alignment. The real
   no-contact image is the per-pixel median of the real tiles (README), each resampled
   onto the tile's pixels through their alignments (a median of crops cut a few px
   apart, as the README's top-left crop does, leaves the image circle's edge in every
   contact region: 4191 and 5048 px of columns 2 and 4, while it reproduces the
   README's numbers, mean change 0.028, 0.134, 0.148); with fewer than
   MIN_MEDIAN_TILES real tiles the published real no-contact image joins the median.
   The contact region is the README's: mean |tile - no-contact| over channels above
   CHANGE_LEVEL, dilated by REGION_DILATION px (``scenes.captures``), inside the image
   circle less a px. ``strength_ratio`` is ``scenes.captures.contact_strength`` of the
   simulation over the real tile's, over that region; ``shape_corr`` the Pearson
   correlation of the change images (each minus its own no-contact frame, signed, all
   channels) inside it. Both renderers are uncalibrated, so the ratio holds their
   exposure too: ``contrast`` splits it per channel into the level ratio (the no-contact
   images over the region: the camera's) and the relative-change ratio (the light's),
   and ``strength_ratio_exposed`` is the simulation seen through the real camera's
   exposure (:func:`exposure`: a gain per channel fitted on the no-contact tiles outside
   the contact region; a channel the real camera clipped over most of the tile, the
   GelTip's blue, is not judged); ``signed_ratio_exposed`` (:func:`signed_change`) is
   whether that change brightens or darkens the region as the real one does, which a
   strength (a mean of |change|) cannot tell. ``noise_strength`` is what the render's
   own Monte Carlo noise alone reads as strength there (:func:`noise_floor`), to tell a
   faint contact from noise.
5. **At the real contact's place** (``at_real_place``): the figure's real and simulated
   contacts of one column need not sit at one place in the frame, so each column is
   scored again with the recovered tap moved by the offset from the published tile's
   contact patch to the real tile's (each patch found as in step 3), its depth and roll
   kept: a translation of the pixel, not a fit to the real tile. Measured on the shared
   tiles: 6 frame px for column 0, but 72 (column 2) and 91 (column 4) frame px farther
   from the image's centre in the real tile than in the published simulation.
6. **Located on the real tile** (``at_real_place.located``): from that place, the fast
   path's render of the contact (its depth held) is moved, and rolled where the object is
   not round, until the magnitude of its change correlates best with the real tile's
   (:func:`locate`), and both renderers are scored there. This fits the place to the
   real tile, never the depth or the strength.

Run ``tactile-sim bench tiles --json PATH`` (``register``), or :func:`run`.
"""

from __future__ import annotations

import json
import math
import re
import sys
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import ndimage, optimize

from phong_reference.bake import METHODS
from scenes.errors import TactileSimError

#: The caption's objects, in the order of the figure's columns.
CAPTION = ("sphere", "cone", "indented_prism", "dots", "open_cylinder")
#: Objects a roll about the normal does not change (searched without roll).
ROUND = ("sphere", "cylinder", "open_cylinder", "cone")
#: Roll symmetry period of objects that are not round, radians (a full turn otherwise).
ROLL_PERIOD_RAD = {"indented_prism": math.pi / 2}
#: The published light fields, and the one whose tile the contact is recovered from.
FIELDS = METHODS
MATCH_FIELD = "linear"
#: The figure's column labels of the simulations' backgrounds.
BACKGROUNDS = ("nonebg", "solidbg", "realbg")
#: A tile's file name: the real sensor or a field, its column, its background label.
TILE_NAME = re.compile(r"^(?P<kind>real|" + "|".join(FIELDS) + r")_col(?P<column>\d+)_(?P<background>"
                       + "|".join(BACKGROUNDS) + r")\.png$")

#: The paper dataset's settings (NOTES.md, "Paper dataset (Table 1)"): i_a, the divisor
#: of the real background image, and the solid background's colour.
PAPER_AMBIENT = 0.8
PAPER_BACKGROUND_DIVISOR = 225.0
PAPER_SOLID_COLOUR = (0.6, 0.5, 0.96)
#: Their membrane, in the camera frame, metres (MANIFEST.txt).
PAPER_MESH = Path("meshes") / "sensor" / "160x120_aligned_mesh.stl"

#: An alignment's scale (frame px per tile px) stays within this share of the frame's
#: height over the tile's (the figure's tiles show the frame's height: measured 2.817-2.821
#: on the 171-173 px tiles, whose height gives 2.775-2.807).
SCALE_SLACK = 0.08
#: An alignment's offsets stay this close to the centred crop's, frame px.
SHIFT_BOUND_PX = 12.0
#: A tile's height must be in this range, px, and its width over height in ASPECT_BOUNDS.
TILE_HEIGHT_BOUNDS_PX = (100, 400)
ASPECT_BOUNDS = (1.2, 1.5)
#: Tile px at each edge left out of every comparison (the figure's white gaps).
BORDER_PX = 3
#: A tile pixel whose mean |difference| over channels exceeds this shows the contact (README).
CHANGE_LEVEL = 0.05
#: Changed pixels this close (tile px) are one patch of a contact.
PATCH_GAP_PX = 2
#: The contact's patch is looked for this far (tile px) inside the image circle.
CIRCLE_MARGIN_PX = 3
#: With fewer real tiles than this, the real no-contact image joins their median.
MIN_MEDIAN_TILES = 3

#: The search (module doc): coarse grid and bounds.
COARSE_OFFSETS_PX = (-12.0, 0.0, 12.0)
COARSE_DEPTHS_MM = (0.5, 1.0, 1.5, 2.0, 3.0)
COARSE_ROLLS = 6
PLACE_BOUND_PX = 50.0
DEPTH_BOUNDS_MM = (0.1, 4.0)
#: The coarse grid and the first refine compare tiles blurred by this, tile px: a wider
#: basin for contacts that show as thin outlines (the indented prism's, in the linear tile).
COARSE_BLUR_PX = 1.5
#: Nelder-Mead's first steps and its budget per refine (evaluations).
STEP_PX, STEP_MM, STEP_RAD = 4.0, 0.25, math.radians(8.0)
REFINE_EVALUATIONS = 160
ALIGN_EVALUATIONS = 200

#: The reference's photons per pass by default (the plugin's default is 2^18).
PHOTONS = 1 << 16


class TileError(TactileSimError, ValueError):
    """A tiles folder or tile that the study cannot use; the message names it."""


# --------------------------------------------------------------------------------------
# The tiles on disk.


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


# --------------------------------------------------------------------------------------
# Tiles and frames.


@dataclass(frozen=True)
class Alignment:
    """Where a tile lies in the frame: tile pixel (row i, column j) is frame pixel
    (u, v) = (offset_u + scale j, offset_v + scale i), pixel centres, px."""

    scale: float
    offset_u: float
    offset_v: float

    def to_frame(self, row, col) -> tuple:
        """Frame (u, v) px of tile (row, column) px."""
        return self.offset_u + self.scale * np.asarray(col), self.offset_v + self.scale * np.asarray(row)

    def to_tile(self, u, v) -> tuple:
        """Tile (row, column) px of frame (u, v) px."""
        return (np.asarray(v) - self.offset_v) / self.scale, (np.asarray(u) - self.offset_u) / self.scale

    def to_dict(self) -> dict:
        return {"scale": self.scale, "offset_u_px": self.offset_u, "offset_v_px": self.offset_v}


def centred(shape: tuple[int, int], frame: tuple[int, int], scale: float | None = None) -> Alignment:
    """The alignment of a tile of ``shape`` (h, w) cut centred from a frame (H, W), px, at
    ``scale`` (default H / h: the tile shows the frame's height)."""
    (h, w), (H, W) = shape, frame
    scale = H / h if scale is None else float(scale)
    return Alignment(scale, (W - 1) / 2 - scale * (w - 1) / 2, (H - 1) / 2 - scale * (h - 1) / 2)


def antialias(image: np.ndarray, scale: float) -> np.ndarray:
    """A frame image (H, W[, C]) blurred for sampling ``scale`` times coarser: Gaussian of
    sigma (scale - 1) / 2 px (scikit-image's ``resize`` anti-aliasing), float64."""
    image = np.asarray(image, np.float64)
    sigma = max(0.0, (scale - 1.0) / 2.0)
    if sigma == 0:
        return image
    return ndimage.gaussian_filter(image, (sigma, sigma) + (0,) * (image.ndim - 2), mode="nearest")


def sample(image: np.ndarray, shape: tuple[int, int], alignment: Alignment, cval: float = 0.0) -> np.ndarray:
    """A frame image (H, W[, C]) sampled bilinearly at a tile's pixels, (h, w[, C]); ``cval``
    beyond the frame."""
    image = np.asarray(image, np.float64)
    rows, cols = np.mgrid[: shape[0], : shape[1]]
    u, v = alignment.to_frame(rows, cols)
    planes = image[..., None] if image.ndim == 2 else image
    out = np.stack([ndimage.map_coordinates(planes[..., c], [v, u], order=1, mode="constant", cval=cval)
                    for c in range(planes.shape[-1])], axis=-1)
    return out[..., 0] if image.ndim == 2 else out


def to_tile(image: np.ndarray, shape: tuple[int, int], alignment: Alignment) -> np.ndarray:
    """A frame image (H, W[, C]) as the figure shows it in a tile of ``shape`` (h, w)."""
    return sample(antialias(image, alignment.scale), shape, alignment)


def inner(shape: tuple[int, int]) -> np.ndarray:
    """(h, w) bool: a tile's pixels but its BORDER_PX edge (the figure's white gaps)."""
    keep = np.zeros(shape, bool)
    keep[BORDER_PX:-BORDER_PX, BORDER_PX:-BORDER_PX] = True
    return keep


def align(tile: np.ndarray, image: np.ndarray, weights: np.ndarray | None = None,
          start: Alignment | None = None) -> tuple[Alignment, float]:
    """The alignment of ``tile`` (h, w, 3) that best shows the frame image ``image``
    (H, W, 3) in it: least weighted mean |difference| (Nelder-Mead, bounded: the
    scale within SCALE_SLACK of the centred crop's, offsets within SHIFT_BOUND_PX of it).
    Returns (alignment, loss).

    weights : (h, w) bool or float, the tile's pixels that count (default: ``inner``).
    """
    tile = np.asarray(tile, np.float64)
    shape = tile.shape[:2]
    w = (inner(shape) if weights is None else np.asarray(weights, np.float64)).astype(np.float64)
    if w.shape != shape or not w.sum() > 0:
        raise ValueError(f"weights must be ({shape[0]}, {shape[1]}) with some weight, got {w.shape}")
    w = w[..., None] / (3.0 * w.sum())
    home = centred(shape, np.shape(image)[:2])
    start = start or home
    blurred = antialias(image, start.scale)  # the blur varies too little over the bounds to redo

    def loss(p):
        return float((np.abs(sample(blurred, shape, Alignment(*p)) - tile) * w).sum())

    x0 = np.array([start.scale, start.offset_u, start.offset_v])
    bounds = [(home.scale * (1 - SCALE_SLACK), home.scale * (1 + SCALE_SLACK)),
              (home.offset_u - SHIFT_BOUND_PX, home.offset_u + SHIFT_BOUND_PX),
              (home.offset_v - SHIFT_BOUND_PX, home.offset_v + SHIFT_BOUND_PX)]
    x0 = np.clip(x0, [b[0] for b in bounds], [b[1] for b in bounds])
    simplex = np.vstack([x0, x0 + [0.02, 0, 0], x0 + [0, 2.0, 0], x0 + [0, 0, 2.0]])
    res = optimize.minimize(loss, x0, method="Nelder-Mead", bounds=bounds,
                            options={"initial_simplex": simplex, "xatol": 1e-3, "fatol": 1e-7,
                                     "maxfev": ALIGN_EVALUATIONS})
    return Alignment(*(float(x) for x in res.x)), float(res.fun)


def change(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(h, w) mean over channels of |a - b|, for (h, w, 3) images."""
    return np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64)).mean(axis=-1)


def changed_region(image: np.ndarray, no_contact: np.ndarray, inside: np.ndarray) -> np.ndarray:
    """(h, w) bool, the README's contact region: mean |image - no_contact| over channels
    above CHANGE_LEVEL, dilated by ``scenes.captures.REGION_DILATION`` px, within ``inside``."""
    from scenes.captures import REGION_DILATION

    hot = (change(image, no_contact) > CHANGE_LEVEL) & inside
    return ndimage.binary_dilation(hot, iterations=REGION_DILATION) & inside


def largest_patch(mask: np.ndarray, weight: np.ndarray | None = None) -> np.ndarray:
    """(h, w) bool: the pixels of ``mask`` in its largest patch (by the sum of ``weight``
    over it, default its pixel count), pixels PATCH_GAP_PX apart counting as joined (a
    contact's thin outline is one patch); all False if none."""
    mask = np.asarray(mask, bool)
    joined = ndimage.binary_dilation(mask, iterations=PATCH_GAP_PX)
    labels, n = ndimage.label(joined, structure=np.ones((3, 3)))
    if n == 0:
        return np.zeros_like(mask)
    weight = np.ones(mask.shape) if weight is None else np.asarray(weight, np.float64)
    sizes = ndimage.sum(weight * mask, labels, index=np.arange(1, n + 1))
    return mask & (labels == 1 + int(np.argmax(sizes)))


# --------------------------------------------------------------------------------------
# The published model.


def paper_spec(spec, background: str):
    """``spec`` (the GelTip's: Table 1's LEDs) with the paper dataset's material for a
    background label: i_a = PAPER_AMBIENT (times 255 / PAPER_BACKGROUND_DIVISOR for
    ``realbg``, whose image is read as /255) and R.V not clamped."""
    from scenes.spec import Material

    if background not in BACKGROUNDS:
        raise ValueError(f"background must be one of {', '.join(BACKGROUNDS)}, got {background!r}")
    ambient = PAPER_AMBIENT * (255.0 / PAPER_BACKGROUND_DIVISOR if background == "realbg" else 1.0)
    return spec.replace(material=Material(ambient=ambient, shininess=spec.material.shininess, clamp_specular=False))


def paper_background(reference_dir: Path, background: str, camera) -> np.ndarray:
    """The background image B of a background label, (H, W, 3) float32 in [0, 1]."""
    from scenes.images import read_rgb

    if background == "nonebg":
        return np.zeros(camera.shape + (3,), np.float32)
    if background == "solidbg":
        return np.broadcast_to(np.asarray(PAPER_SOLID_COLOUR, np.float32), camera.shape + (3,)).copy()
    if background == "realbg":
        return read_rgb(Path(reference_dir) / "real" / "bkg.png", camera.shape)
    raise ValueError(f"background must be one of {', '.join(BACKGROUNDS)}, got {background!r}")


@dataclass
class PaperModel:
    """The published model's shared inputs: the spec, camera, their D_ref (H, W) m, their
    membrane mesh, the Sobel normals of D_ref (3, H, W) and the folder of their data."""

    reference_dir: Path
    spec: object
    camera: object
    ref_depth: np.ndarray
    mesh: object
    normals: np.ndarray
    _renderers: dict = field(default_factory=dict)

    @classmethod
    def load(cls, reference_dir: Path) -> "PaperModel":
        from scenes.camera import Camera
        from scenes.geometry import load_mesh
        from scenes.spec import default_spec
        from studies.reproduce_published import sobel_normals

        spec = default_spec()
        camera = Camera.from_spec(spec)
        ref_depth = np.load(Path(reference_dir) / "sim_depth" / "bkg.npy")
        mesh = load_mesh(Path(reference_dir) / PAPER_MESH, "m")
        return cls(Path(reference_dir), spec, camera, ref_depth, mesh, sobel_normals(ref_depth, camera))

    def renderer(self, method: str, background: str):
        """Their model with one field and background label (a ``phong_reference`` Renderer)."""
        key = (method, background)
        if key not in self._renderers:
            from phong_reference.render import Renderer
            from studies.reproduce_published import RECTIFIED, load_published_fields, prepare_fields

            L = prepare_fields(load_published_fields(self.reference_dir, method), self.camera.shape,
                               self.normals if RECTIFIED[method] else None)
            self._renderers[key] = Renderer(paper_spec(self.spec, background), self.camera, self.ref_depth, L,
                                            paper_background(self.reference_dir, background, self.camera))
        return self._renderers[key]


def published(image: np.ndarray) -> np.ndarray:
    """A render as the published code saved it (8-bit, truncated: ``to_8bit``)."""
    from studies.reproduce_published import to_8bit

    return to_8bit(image)


# --------------------------------------------------------------------------------------
# Recovery.


@dataclass(frozen=True)
class Contact:
    """A tap: the object pressed along the membrane's normal where the camera sees pixel
    (u, v) px, ``depth_m`` deep, rolled ``roll_rad`` about the normal (``press``)."""

    u: float
    v: float
    depth_m: float
    roll_rad: float = 0.0

    def depth_map(self, ref_depth, camera, mesh, shape) -> np.ndarray:
        """(H, W) float32 m, the contact's depth map on a membrane (``scenes.contact.press``)."""
        from scenes.contact import press

        return press(ref_depth, camera, mesh, shape, (self.u, self.v), self.depth_m, self.roll_rad)


@dataclass(frozen=True)
class Recovery:
    """What ``recover`` found: the contact, the tile's alignment, the mean squared error
    over the tile's inner pixels, the contact patch's centroid the search started from
    (frame u, v px) and the number of renders it took."""

    contact: Contact
    alignment: Alignment
    mse: float
    centroid: tuple[float, float]
    evaluations: int


def roll_period(name: str) -> float | None:
    """An object's roll symmetry period, radians; None for a round one (no roll searched)."""
    from scenes.indenters import ball_diameter

    if name in ROUND or ball_diameter(name) is not None:
        return None
    return ROLL_PERIOD_RAD.get(name, 2 * math.pi)


class TileMatch:
    """The error of a contact's published render against one tile: renders a contact on a
    model (a ``phong_reference`` Renderer, its membrane ``mesh`` and the object's
    ``shape``), brings it to the tile and scores it, remembering every evaluation.
    ``blur_px``: both the tile and the render blurred by a Gaussian of that sigma, tile px
    (0: as they are)."""

    def __init__(self, tile: np.ndarray, renderer, mesh, shape, alignment: Alignment, weights=None):
        self.tile = np.asarray(tile, np.float64)
        self.renderer, self.mesh, self.shape = renderer, mesh, shape
        self.weights = inner(self.tile.shape[:2]) if weights is None else np.asarray(weights, bool)
        self.alignment = alignment
        self.blur_px = 0.0
        self.evaluations = 0
        self._memo: dict = {}  # (pose, alignment, blur) -> mse; frames are not kept (3.7 MB each)

    def _blur(self, image: np.ndarray) -> np.ndarray:
        if self.blur_px == 0:
            return image
        return ndimage.gaussian_filter(image, (self.blur_px, self.blur_px, 0), mode="nearest")

    def image(self, contact: Contact | None) -> np.ndarray:
        """The model's published frame (H, W, 3) of a contact (None: no contact)."""
        r = self.renderer
        if contact is None:
            return published(r.base)
        return published(r.render(contact.depth_map(r.ref_depth, r.camera, self.mesh, self.shape)))

    def mse(self, contact: Contact) -> float:
        """Mean squared error over the tile's weighted pixels; inf for a contact that cannot
        be pressed (a pixel off the membrane, a depth out of bounds)."""
        pose = (round(contact.u, 3), round(contact.v, 3), round(contact.depth_m * 1e3, 4),
                round(contact.roll_rad, 4))
        key = pose + (self.alignment, self.blur_px)
        if key not in self._memo:
            try:
                image = self.image(contact)
            except ValueError:
                self._memo[key] = math.inf
            else:
                self.evaluations += 1
                err = self._blur(to_tile(image, self.tile.shape[:2], self.alignment)) - self._blur(self.tile)
                self._memo[key] = float(np.mean(err[self.weights] ** 2))
        return self._memo[key]


def contact_centroid(tile: np.ndarray, no_contact_tile: np.ndarray, alignment: Alignment, camera,
                     where: str = "tile") -> tuple[float, float]:
    """Frame (u, v) px of the centroid of the largest patch (by its sum of change) where the
    tile differs from the no-contact render by more than CHANGE_LEVEL, inside the image
    circle less CIRCLE_MARGIN_PX (its edge shows any crop error); TileError naming ``where``
    if there is none."""
    diff = change(tile, no_contact_tile)
    inside = tile_inside(tile.shape[:2], alignment, camera, CIRCLE_MARGIN_PX)
    patch = largest_patch((diff > CHANGE_LEVEL) & inside, diff)
    if not patch.any():
        raise TileError(f"{where}: no contact found: no patch of the tile differs from its no-contact image by "
                        f"more than {CHANGE_LEVEL} (mean over channels)")
    rows, cols = np.nonzero(patch)
    u, v = alignment.to_frame(rows.mean(), cols.mean())
    return float(u), float(v)


def _refine(match: TileMatch, best: Contact, centre: tuple[float, float], period: float | None,
            evaluations: int) -> Contact:
    """A bounded Nelder-Mead from ``best`` (module doc's bounds)."""
    lo_mm, hi_mm = DEPTH_BOUNDS_MM
    bounds = [(centre[0] - PLACE_BOUND_PX, centre[0] + PLACE_BOUND_PX),
              (centre[1] - PLACE_BOUND_PX, centre[1] + PLACE_BOUND_PX), (lo_mm, hi_mm)]
    steps = [STEP_PX, STEP_PX, STEP_MM]
    x0 = [best.u, best.v, best.depth_m * 1e3]
    if period is not None:
        roll_step = period / COARSE_ROLLS
        bounds.append((best.roll_rad - roll_step, best.roll_rad + roll_step))
        steps.append(min(STEP_RAD, roll_step / 2))
        x0.append(best.roll_rad)
    x0 = np.clip(np.asarray(x0, np.float64), [b[0] for b in bounds], [b[1] for b in bounds])
    scale = np.asarray(steps)

    def contact(y):
        x = y * scale
        return Contact(float(x[0]), float(x[1]), float(x[2]) * 1e-3, float(x[3]) if period is not None else 0.0)

    y0 = x0 / scale
    simplex = np.vstack([y0] + [y0 + np.eye(len(y0))[i] for i in range(len(y0))])
    res = optimize.minimize(lambda y: match.mse(contact(y)), y0, method="Nelder-Mead",
                            bounds=[(b[0] / s, b[1] / s) for b, s in zip(bounds, scale)],
                            options={"initial_simplex": simplex, "xatol": 0.05, "fatol": 1e-8, "maxfev": evaluations})
    found = contact(res.x)
    return found if match.mse(found) <= match.mse(best) else best


def recover(tile: np.ndarray, renderer, mesh, shape, period: float | None = None, *,
            offsets_px=COARSE_OFFSETS_PX, depths_mm=COARSE_DEPTHS_MM, rolls: int = COARSE_ROLLS,
            evaluations: int = REFINE_EVALUATIONS, where: str = "tile") -> Recovery:
    """The contact whose published render best matches ``tile`` (module doc, step 3).

    Parameters
    ----------
    tile : (h, w, 3) float in [0, 1], the published simulation's tile.
    renderer : the published model for the tile's field and background (a
        ``phong_reference.render.Renderer``: its camera, D_ref, no-contact ``base``).
    mesh : the membrane the contact is pressed on (``scenes.contact.surface_point``).
    shape : the object, a trimesh in the indenters' frame (``scenes.indenters``).
    period : its roll symmetry period, radians (``roll_period``); None: round, no roll.
    offsets_px, depths_mm, rolls : the coarse grid; evaluations : each refine's budget.
    where : names the tile in errors.
    """
    tile = np.asarray(tile, np.float64)
    if tile.ndim != 3 or tile.shape[-1] != 3:
        raise ValueError(f"tile must be (h, w, 3) float, got shape {tile.shape}")
    shape_hw = tile.shape[:2]
    base = published(renderer.base)
    # Align on the no-contact render, then again without the contact's patch.
    alignment, _ = align(tile, base)
    camera = renderer.camera
    centre = contact_centroid(tile, to_tile(base, shape_hw, alignment), alignment, camera, where)
    patch = ndimage.binary_dilation(change(tile, to_tile(base, shape_hw, alignment)) > CHANGE_LEVEL, iterations=4)
    alignment, _ = align(tile, base, inner(shape_hw) & ~patch, alignment)
    centre = contact_centroid(tile, to_tile(base, shape_hw, alignment), alignment, camera, where)

    match = TileMatch(tile, renderer, mesh, shape, alignment)
    match.blur_px = COARSE_BLUR_PX
    roll_grid = [0.0] if period is None else [period * k / rolls for k in range(rolls)]
    grid = [Contact(centre[0] + du, centre[1] + dv, d * 1e-3, r)
            for du in offsets_px for dv in offsets_px for d in depths_mm for r in roll_grid]
    scores = [match.mse(c) for c in grid]
    if not np.isfinite(scores).any():
        raise TileError(f"{where}: no contact of the coarse grid about frame pixel ({centre[0]:.0f}, "
                        f"{centre[1]:.0f}) could be pressed on the membrane")
    best = _refine(match, grid[int(np.argmin(scores))], centre, period, evaluations)
    match.blur_px = 0.0
    best = _refine(match, best, centre, period, evaluations)
    # Align once more on the recovered render, contact and all, and refine again.
    alignment, _ = align(tile, match.image(best), start=alignment)
    match.alignment = alignment
    best = _refine(match, best, centre, period, evaluations // 2)
    if period is not None:
        best = Contact(best.u, best.v, best.depth_m, float(best.roll_rad % period))
    return Recovery(best, alignment, match.mse(best), centre, match.evaluations)


def match_report(tile: np.ndarray, renderer, mesh, shape, contact: Contact) -> dict:
    """How well a contact explains a tile of one field: the tile aligned to the contact's
    render, then the MAE of that render and of the no-contact render over the tile's
    inner pixels and over the tile's contact (``changed_region`` against the no-contact
    render), and the alignment."""
    shape_hw = tile.shape[:2]
    image = published(renderer.render(contact.depth_map(renderer.ref_depth, renderer.camera, mesh, shape)))
    alignment, _ = align(tile, image)
    keep = inner(shape_hw)
    sim = to_tile(image, shape_hw, alignment)
    none = to_tile(published(renderer.base), shape_hw, alignment)
    region = changed_region(tile, none, keep)
    err, err_none = change(sim, tile), change(none, tile)
    return {"mae": float(err[keep].mean()), "no_contact_mae": float(err_none[keep].mean()),
            "mae_contact": _mean(err, region), "no_contact_mae_contact": _mean(err_none, region),
            "contact_px": int(region.sum()), "alignment": alignment.to_dict()}


def _mean(values: np.ndarray, where: np.ndarray) -> float | None:
    return float(values[where].mean()) if where.any() else None


# --------------------------------------------------------------------------------------
# Against the real tile.


def real_alignment(tile: np.ndarray, real_background: np.ndarray) -> Alignment:
    """A real tile's alignment to the published real no-contact image (H, W, 3): fitted on
    every inner pixel, then again without where the tile differs from it (the contact)."""
    shape_hw = tile.shape[:2]
    alignment, _ = align(tile, real_background)
    hot = change(tile, to_tile(real_background, shape_hw, alignment)) > CHANGE_LEVEL
    alignment, _ = align(tile, real_background, inner(shape_hw) & ~ndimage.binary_dilation(hot, iterations=2),
                         alignment)
    return alignment


def real_no_contact(tiles: dict[int, np.ndarray], alignments: dict[int, Alignment],
                    real_background: np.ndarray | None = None) -> tuple[dict[int, np.ndarray], str]:
    """Each real tile's no-contact image at its own pixels: the per-pixel median of every
    real tile resampled there (through their alignments); with fewer than
    MIN_MEDIAN_TILES tiles, the published real no-contact image (H, W, 3), brought to the
    tile, fills the median up to that many members. Returns ({column: (h, w, 3)}, how it
    was made)."""
    fill = max(0, MIN_MEDIAN_TILES - len(tiles))
    with_background = fill > 0
    if with_background and real_background is None:
        raise ValueError(f"fewer than {MIN_MEDIAN_TILES} real tiles need the real no-contact image for the median")
    out = {}
    for k, tile in tiles.items():
        shape_hw = tile.shape[:2]
        rows, cols = np.mgrid[: shape_hw[0], : shape_hw[1]]
        u, v = alignments[k].to_frame(rows, cols)
        stack = []
        for j, other in tiles.items():
            r, c = alignments[j].to_tile(u, v)
            stack.append(np.stack([ndimage.map_coordinates(other[..., ch], [r, c], order=1, mode="constant",
                                                           cval=np.nan) for ch in range(3)], axis=-1))
        if fill:
            stack += [to_tile(real_background, shape_hw, alignments[k])] * fill
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN pixels: none of the tiles reaches them
            median = np.nanmedian(np.stack(stack), axis=0)
        out[k] = np.where(np.isfinite(median), median, tile)
    how = (f"per-pixel median of the {len(tiles)} real tiles, each resampled onto the tile's pixels through their "
           "alignments" + (f", with the published real no-contact image as {fill} more" if with_background else ""))
    return out, how


def tile_inside(shape: tuple[int, int], alignment: Alignment, camera, margin_px: int = 1) -> np.ndarray:
    """(h, w) bool: a tile's inner pixels inside the camera's image circle, less
    ``margin_px`` tile px."""
    circle = sample(camera.mask.astype(np.float64), shape, alignment) > 0.999
    return ndimage.binary_erosion(circle, iterations=margin_px) & inner(shape)


def pearson(a: np.ndarray, b: np.ndarray) -> float | None:
    """Pearson correlation of two equal-size arrays (flattened); None when either is constant."""
    a, b = np.ravel(a).astype(np.float64), np.ravel(b).astype(np.float64)
    if a.size < 2 or a.std() == 0 or b.std() == 0:
        return None
    return float(np.corrcoef(a, b)[0, 1])


def _ratio(a: float, b: float) -> float | None:
    return a / b if b > 0 and math.isfinite(a) and math.isfinite(b) else None


def exposure(sim_no_contact: np.ndarray, real_nc: np.ndarray, where: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The camera's exposure that one no-contact image pins down, per channel: (gains (3,),
    judged (3,) bool). Each gain brings the simulation's no-contact tile to the real one's
    by least squares over the pixels of ``where`` (h, w) that the real camera did not clip
    (below ``pbr_tactile.real_image.CLIP_LEVEL``). A channel clipped over more than
    ``SATURATED_SHARE`` of ``where`` shows no contact and is not judged (as the
    calibration censors it); nor is a channel the simulation leaves dark (its mean there
    below ``CIRCLE_THRESHOLD``, an unlit pixel's level: a fast path without its background
    term), whose gain would be its noise's."""
    from pbr_tactile.real_image import CIRCLE_THRESHOLD, CLIP_LEVEL, SATURATED_SHARE

    gains, judged = np.zeros(3), np.zeros(3, bool)
    for c in range(3):
        s, r = sim_no_contact[..., c][where], real_nc[..., c][where]
        ok = r < CLIP_LEVEL
        if not ok.any():
            continue
        ss = float(np.sum(s[ok] ** 2))
        gains[c] = float(np.sum(s[ok] * r[ok])) / ss if ss > 0 else 0.0
        judged[c] = (1.0 - ok.mean()) <= SATURATED_SHARE and gains[c] > 0 and s.mean() >= CIRCLE_THRESHOLD
    return gains, judged


def score(sim: np.ndarray, sim_no_contact: np.ndarray, real: np.ndarray, real_nc: np.ndarray,
          region: np.ndarray, inside: np.ndarray | None = None) -> dict:
    """A simulated tile (h, w, 3) against the real one over the contact region (h, w):
    ``strength`` (``scenes.captures.contact_strength``), ``strength_ratio`` (sim over real)
    and ``shape_corr`` (Pearson of the signed change images there, all channels).

    With ``inside`` (the tile's image circle), also the strength's two factors per channel
    (``contrast``: ``level_ratio``, the no-contact images' means over the region, sim over
    real, which is the camera's; ``relative_ratio``, the change over the level, which is
    the light's; ``scenes.captures.contact_contrast``), and ``exposed``: the simulation
    seen through the real camera's exposure (``exposure``, fitted on ``inside`` less the
    region, so never on the contact), its strength, ratio and shape over the judged
    (unsaturated) channels."""
    from scenes.captures import contact_contrast, contact_strength

    s_sim = float(contact_strength(sim[None], sim_no_contact, region[None])[0])
    s_real = float(contact_strength(real[None], real_nc, region[None])[0])
    corr = pearson((sim - sim_no_contact)[region], (real - real_nc)[region]) if region.any() else None
    out = {"strength": s_sim if math.isfinite(s_sim) else None, "strength_ratio": _ratio(s_sim, s_real),
           "shape_corr": corr}
    if inside is None or not region.any():
        return out
    cs = contact_contrast(sim[None], sim_no_contact, region[None])
    cr = contact_contrast(real[None], real_nc, region[None])
    out["contrast"] = {key: [_ratio(float(a), float(b)) for a, b in zip(cs[name][0], cr[name][0])]
                       for key, name in (("level_ratio", "level"), ("relative_ratio", "relative"))}
    gains, judged = exposure(sim_no_contact, real_nc, inside & ~region)
    if judged.any():
        e_sim = float(np.mean(gains[judged] * cs["change"][0][judged]))
        e_real = float(np.mean(cr["change"][0][judged]))
        d_sim = ((sim - sim_no_contact) * gains)[region][:, judged]
        d_real = (real - real_nc)[region][:, judged]
        out["exposed"] = {
            "gains": gains.tolist(), "channels": "".join(ch for ch, j in zip("rgb", judged) if j),
            "strength": e_sim, "strength_real": e_real, "strength_ratio": _ratio(e_sim, e_real),
            "shape_corr": pearson(d_sim, d_real), **signed_change(d_sim, d_real)}
    return out


def signed_change(sim_change: np.ndarray, real_change: np.ndarray) -> dict:
    """Whether a contact brightens or darkens the region as the real one does, which the
    strength (a mean of |change|) cannot tell: ``signed``, the mean signed change per
    channel over the region's pixels (N, C) of each, and ``signed_ratio``, the
    simulation's mean change projected on the real's, (m_sim . m_real) / |m_real|^2: 1
    when it changes the region's colour by as much and the same way, 0 when not along it,
    negative when it darkens what the real contact brightens. None where the real
    change's mean is 0. A ValueError where the two are not of one (N, C) shape."""
    sim_change, real_change = np.asarray(sim_change, np.float64), np.asarray(real_change, np.float64)
    if real_change.ndim != 2 or sim_change.shape != real_change.shape:
        raise ValueError(f"sim_change and real_change must be (N, C) pixels by channels of one shape, got "
                         f"{sim_change.shape} and {real_change.shape}")
    m_sim, m_real = sim_change.mean(axis=0), real_change.mean(axis=0)
    norm = float(m_real @ m_real)
    return {"signed": {"sim": m_sim.tolist(), "real": m_real.tolist()},
            "signed_ratio": float(m_sim @ m_real) / norm if norm > 0 and np.isfinite(norm) else None}


#: A change image is shown as 0.5 + CHANGE_VIEW_GAIN * change: mid grey where nothing
#: changes, brighter where the contact brightens the tile (``change_figure``).
CHANGE_VIEW_GAIN = 2.0


def change_figure(real: np.ndarray, real_nc: np.ndarray, region: np.ndarray, sims: dict) -> np.ndarray:
    """A column's contacts to judge by eye, one row (h, W, 3) in [0, 1]: the real tile,
    its change (0.5 + CHANGE_VIEW_GAIN * (real - no-contact)) and its contact region
    (white), then for each renderer of ``sims`` ({name: (tile, no-contact tile, gains
    (3,))}) its no-contact tile and its change, each times the gains (the real camera's
    exposure, ``exposure``), so the sign and shape of both changes read on one scale. A
    ValueError names a tile whose shape is not the real tile's (h, w, 3)."""
    real, real_nc = np.asarray(real, np.float64), np.asarray(real_nc, np.float64)
    if real.ndim != 3 or real.shape[2] != 3 or real_nc.shape != real.shape:
        raise ValueError(f"real and real_nc must be (h, w, 3) tiles of one shape, got {real.shape} and "
                         f"{real_nc.shape}")
    if np.shape(region) != real.shape[:2]:
        raise ValueError(f"region must be the tile's (h, w) {real.shape[:2]}, got {np.shape(region)}")

    def view(change):
        return 0.5 + CHANGE_VIEW_GAIN * change

    panels = [real, view(real - real_nc), np.repeat(np.asarray(region, np.float64)[..., None], 3, axis=2)]
    for name, (sim, sim_nc, gains) in sims.items():
        sim, sim_nc = np.asarray(sim, np.float64), np.asarray(sim_nc, np.float64)
        if sim.shape != real.shape or sim_nc.shape != real.shape:
            raise ValueError(f"{name}: its tile and no-contact tile must be the real tile's {real.shape}, got "
                             f"{sim.shape} and {sim_nc.shape}")
        g = np.asarray(gains, np.float64).reshape(3)
        panels += [sim_nc * g, view((sim - sim_nc) * g)]
    return np.clip(np.concatenate(panels, axis=1), 0.0, 1.0)


# --------------------------------------------------------------------------------------
# The benchmark.


def _clean(obj):
    """JSON-safe: NaN and inf as None, numpy scalars as Python numbers."""
    if isinstance(obj, dict):
        return {str(k): _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    if isinstance(obj, (np.floating, float)):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, np.integer):
        return int(obj)
    return obj


def simulated(contact: Contact, renderers: dict, shape, spec_inputs: tuple, real: np.ndarray, real_nc: np.ndarray,
              alignment: Alignment, region: np.ndarray, inside: np.ndarray | None = None,
              keep: dict | None = None) -> tuple[dict, dict]:
    """Each renderer's tile of a contact pressed on our membrane (``spec_inputs``: D_ref,
    camera, mesh), scored against the real tile (``score``, over ``inside`` for its
    exposure, with the renderer's record: the reference's passes and contact RSE):
    ({name: score}, {name: s}). ``keep``, a dict: each renderer's (tile, no-contact tile,
    exposure gains) put in it, for ``change_figure``."""
    from scenes.generate import render_sample

    ref_depth, camera, mesh = spec_inputs
    try:
        depth = contact.depth_map(ref_depth, camera, mesh, shape)
    except ValueError as exc:
        return {name: {"strength": None, "strength_ratio": None, "shape_corr": None, "error": str(exc)}
                for name in renderers}, {}
    shape_hw = real.shape[:2]
    scores, seconds = {}, {}
    for name, r in renderers.items():
        t0 = time.perf_counter()
        out = render_sample(r, depth)
        seconds[name] = time.perf_counter() - t0
        tile, nc_tile = to_tile(out["image"], shape_hw, alignment), to_tile(r.no_contact, shape_hw, alignment)
        sc = score(tile, nc_tile, real, real_nc, region, inside)
        if keep is not None:
            keep[name] = (tile, nc_tile, (sc.get("exposed") or {}).get("gains", [1.0, 1.0, 1.0]))
        noise = image_noise(r, out)
        if noise is not None and region.any():
            sc.update(noise_floor([to_tile(n, shape_hw, alignment) for n in noise], region, sc))
        scores[name] = {**sc, **{k: v for k, v in out["record"].items() if k in ("passes", "contact_rse")}}
    return scores, seconds


#: Noise images drawn per render to read what its noise alone shows (``noise_floor``).
NOISE_DRAWS = 4


def image_noise(renderer, out: dict, draws: int = NOISE_DRAWS, seed: int = 0) -> list[np.ndarray] | None:
    """``draws`` (H, W, 3) images of a Monte Carlo render's noise alone: zero-mean Gaussian
    film pixels of the render's standard error (its variance of the mean,
    ``arrays["variance"]``, block-averaged back to the film), brought to the camera's size
    as the render's image is (the renderer's ``camera_size``) and seen at its exposure
    ``gain`` in its image circle; None for a renderer without a variance (the fast path) or
    with a profile's image model."""
    variance = out["arrays"].get("variance")
    gain = getattr(renderer, "gain", None)
    if variance is None or gain is None or getattr(renderer, "profile", None) is not None:
        return None
    from scenes.images import block_mean

    variance = np.maximum(np.asarray(variance, np.float64), 0.0)
    factor = variance.shape[1] // renderer.opts["film"][0]
    sigma = np.sqrt(block_mean(variance, factor) if factor > 1 else variance)
    rng = np.random.default_rng(seed)
    mask = renderer.camera.mask[..., None]
    return [gain * np.asarray(renderer.camera_size(sigma * rng.standard_normal(sigma.shape)), np.float64) * mask
            for _ in range(draws)]


def noise_floor(noise_tiles: list[np.ndarray], region: np.ndarray, sc: dict) -> dict:
    """What a render's own noise alone reads as contact strength over the region: the
    mean |change| of its noise images (``image_noise``, brought to the tile), all channels
    (``noise_strength``) and, through the exposure, the judged ones
    (``exposed.noise_strength``). A strength within a few of these is noise's."""
    per_channel = np.mean([np.abs(t[region]).mean(axis=0) for t in noise_tiles], axis=0)
    out = {"noise_strength": float(per_channel.mean())}
    e = sc.get("exposed")
    if e is not None:
        judged = np.array([ch in e["channels"] for ch in "rgb"])
        e["noise_strength"] = float(np.mean(np.asarray(e["gains"])[judged] * per_channel[judged]))
    return out


#: The real place's search (``locate``): how far from its start, frame px, and renders.
LOCATE_BOUND_PX = 30.0
LOCATE_EVALUATIONS = 80


def locate(contact: Contact, renderer, shape, spec_inputs: tuple, real: np.ndarray, real_nc: np.ndarray,
           alignment: Alignment, inside: np.ndarray, period: float | None = None) -> tuple[Contact, float]:
    """The place (and roll, for an object that is not round) at which ``renderer`` (the
    fast path) shows the contact whose change best correlates with the real tile's, its
    depth held: Pearson correlation of the change's magnitudes (mean |image - no-contact|
    over channels, unsigned: the real sensor's shading is not the model's) over
    ``inside``, by bounded Nelder-Mead within LOCATE_BOUND_PX of ``contact``. Returns
    (contact there, its correlation)."""
    from scenes.generate import render_sample

    ref_depth, camera, mesh = spec_inputs
    shape_hw = real.shape[:2]
    real_change = change(real, real_nc)[inside]
    nc_tile = to_tile(renderer.no_contact, shape_hw, alignment)

    def at(x) -> Contact:
        return Contact(contact.u + x[0], contact.v + x[1], contact.depth_m,
                       contact.roll_rad + (x[2] if period is not None else 0.0))

    def loss(x) -> float:
        try:
            depth = at(x).depth_map(ref_depth, camera, mesh, shape)
        except ValueError:
            return 1.0
        corr = pearson(change(to_tile(render_sample(renderer, depth)["image"], shape_hw, alignment), nc_tile)[inside],
                       real_change)
        return 1.0 if corr is None else -corr

    b = LOCATE_BOUND_PX
    x0 = np.zeros(3 if period is not None else 2)
    bounds = [(-b, b), (-b, b)] + ([(-period / 2, period / 2)] if period is not None else [])
    simplex = np.vstack([x0] + [x0 + np.eye(len(x0))[i] * (6.0 if i < 2 else period / 8) for i in range(len(x0))])
    res = optimize.minimize(loss, x0, method="Nelder-Mead", bounds=bounds,
                            options={"initial_simplex": simplex, "xatol": 0.25, "fatol": 1e-4,
                                     "maxfev": LOCATE_EVALUATIONS})
    return at(res.x), -float(res.fun)


def _by_renderer(scores: dict, key: str) -> dict:
    return {name: scores.get(name, {}).get(key) for name in ("pbr", "phong")}


def _factors(scores: dict) -> dict:
    """A place's scores beyond the plain strength (``score``): each renderer's ``contrast``
    and ``exposed`` blocks, ``strength_ratio_exposed`` and ``signed_ratio_exposed``
    (``signed_change``) on their own, and what its noise alone reads as strength
    (``noise_strength``, ``noise_floor``)."""
    exposed = _by_renderer(scores, "exposed")
    return {"strength_ratio_exposed": {n: (e or {}).get("strength_ratio") for n, e in exposed.items()},
            "signed_ratio_exposed": {n: (e or {}).get("signed_ratio") for n, e in exposed.items()},
            "contrast": _by_renderer(scores, "contrast"), "exposed": exposed,
            "noise_strength": _by_renderer(scores, "noise_strength")}


def run(json_path, tiles_dir=None, reference_dir=None, objects: dict[int, str] | None = None,
        reference: bool = True, photons: int = PHOTONS, quiet: bool = True, effects: tuple[str, ...] = (),
        images_dir=None) -> dict:
    """The benchmark (module doc): every column of ``tiles_dir`` recovered and scored;
    writes ``json_path`` atomically and returns what it wrote. ``effects``: the
    reference's effects as NAME=VALUE settings (``pbr_tactile.effects.Effects``; none:
    its defaults), to judge a change of its physics on the real tiles. ``images_dir``:
    each column's ``change_figure`` written there, ``colK_recovered.png`` and
    ``colK_at_real_place.png``, and their paths in ``tiles.K.images``.

    Besides the recovered tap, each column is scored with the tap moved by the offset
    between the real tile's contact patch and the published tile's (``at_real_place``:
    the figure's real and simulated contacts of a column need not sit at one place)."""
    from scenes.camera import Camera, reference_depth
    from scenes.captures import REGION_DILATION, contact_strength
    from scenes.contact import surface_point
    from scenes.dataset import atomic_write_json
    from scenes.generate import make_renderer, renderer_plugin
    from scenes.geometry import membrane_mesh
    from scenes.images import read_rgb, write_rgb
    from scenes.indenters import indenter, is_indenter
    from scenes.reference_data import require_real_contacts_dir, require_reference_dir
    from scenes.spec import default_spec

    from pbr_tactile.effects import Effects

    if effects and not reference:
        raise TileError("--effects sets the reference's physics; it has no use with --no-reference")
    Effects().with_settings(list(effects))  # a bad setting is named before any work
    t_all = time.perf_counter()

    def say(text):
        if not quiet:
            print(text, file=sys.stderr, flush=True)

    tiles_dir = require_real_contacts_dir(tiles_dir)
    columns = discover(tiles_dir)
    names = {k: object_of(k, objects) for k in columns}
    for k, name in names.items():
        if not is_indenter(name):
            raise TileError(f"column {k}: object {name!r} is not an indenter (scenes.indenters.INDENTERS, "
                            "ball_<D>mm or a mesh file)")
    reals = {k: read_tile(c.real) for k, c in columns.items()}
    sims = {k: {f: read_tile(p) for f, (p, _) in c.sims.items()} for k, c in columns.items()}
    reference_dir = require_reference_dir(reference_dir)

    t0 = time.perf_counter()
    model = PaperModel.load(reference_dir)
    real_background = read_rgb(reference_dir / "real" / "bkg.png", model.camera.shape).astype(np.float64)
    alignments = {k: real_alignment(t, real_background) for k, t in reals.items()}
    no_contacts, how = real_no_contact(reals, alignments, real_background)
    spec = default_spec()
    camera = Camera.from_spec(spec)
    mesh = membrane_mesh(spec)
    ours = (reference_depth(mesh, camera)[0], camera, mesh)
    renderers = {}
    phong = renderer_plugin("phong")
    phong.prepare(spec, mesh, camera, {})
    renderers["phong"] = make_renderer(phong, spec, mesh, camera, ours[0], {})
    pbr_options = {"photons": int(photons), **({"effects": list(effects)} if effects else {})}
    pbr_settings = None
    if reference:
        pbr = renderer_plugin("pbr")
        say(f"reference: its no-contact frame at {photons} photons per pass (cached after the first run)")
        pbr_settings = pbr.prepare(spec, mesh, camera, pbr_options)
        renderers["pbr"] = make_renderer(pbr, spec, mesh, camera, ours[0], pbr_options)
    stage_seconds = {"prepare": time.perf_counter() - t0}

    out_tiles = {}
    for k, col in columns.items():
        t_col = time.perf_counter()
        name, shape = names[k], indenter(names[k])
        period = roll_period(name)
        match_path, match_bg = col.sims[MATCH_FIELD]
        say(f"column {k}: {name}, recovered from {match_path.name}")
        t0 = time.perf_counter()
        rec = recover(sims[k][MATCH_FIELD], model.renderer(MATCH_FIELD, match_bg), model.mesh, shape, period,
                      where=str(match_path))
        t_recover = time.perf_counter() - t0
        c = rec.contact
        point, normal = surface_point(model.mesh, model.camera, (c.u, c.v))
        fields = {f: match_report(sims[k][f], model.renderer(f, bg), model.mesh, shape, c)
                  for f, (_, bg) in col.sims.items()}
        say(f"  place ({c.u:.1f}, {c.v:.1f}) px, depth {c.depth_m * 1e3:.2f} mm, roll {math.degrees(c.roll_rad):.1f} "
            f"deg; {MATCH_FIELD} contact MAE {fields[MATCH_FIELD]['mae_contact']:.4f} (no contact "
            f"{fields[MATCH_FIELD]['no_contact_mae_contact']:.4f}), {rec.evaluations} renders, {t_recover:.0f} s")

        real, real_nc, align_real = reals[k], no_contacts[k], alignments[k]
        inside = tile_inside(real.shape[:2], align_real, camera)
        region = changed_region(real, real_nc, inside)
        real_strength = float(contact_strength(real[None], real_nc, region[None])[0])
        figures = {}

        def figure(key: str, kept: dict | None) -> None:
            if kept:
                figures[key] = str(write_rgb(Path(images_dir) / f"col{k}_{key}.png",
                                             change_figure(real, real_nc, region, kept)))

        kept = {} if images_dir is not None else None
        scores, seconds = simulated(c, renderers, shape, ours, real, real_nc, align_real, region, inside, kept)
        figure("recovered", kept)
        for rname, sc in scores.items():
            say(f"  {rname}: strength ratio {sc['strength_ratio']} (exposed {(sc.get('exposed') or {}).get('strength_ratio')}"
                f", signed {(sc.get('exposed') or {}).get('signed_ratio')}, noise alone {sc.get('noise_strength')}), "
                f"shape corr {sc['shape_corr']} "
                f"({seconds.get(rname, 0):.0f} s)")
        try:
            real_centre = contact_centroid(real, real_nc, align_real, camera, str(col.real))
        except TileError:
            real_centre = None
        moved = None
        if real_centre is not None:
            offset = (real_centre[0] - rec.centroid[0], real_centre[1] - rec.centroid[1])
            there = Contact(c.u + offset[0], c.v + offset[1], c.depth_m, c.roll_rad)
            kept = {} if images_dir is not None else None
            moved_scores, moved_seconds = simulated(there, renderers, shape, ours, real, real_nc, align_real, region,
                                                    inside, kept)
            figure("at_real_place", kept)
            moved = {"offset_px": list(offset), "u_px": there.u, "v_px": there.v,
                     "strength_ratio": _by_renderer(moved_scores, "strength_ratio"),
                     "shape_corr": _by_renderer(moved_scores, "shape_corr"),
                     "strength": _by_renderer(moved_scores, "strength"), **_factors(moved_scores),
                     "seconds": {f"render_{n}": v for n, v in moved_seconds.items()}}
            say(f"  at the real contact's place (moved {offset[0]:+.0f}, {offset[1]:+.0f} px): strength ratio "
                f"{moved['strength_ratio']}, shape corr {moved['shape_corr']}")
            found, corr = locate(there, renderers["phong"], shape, ours, real, real_nc, align_real, inside, period)
            found_scores, found_seconds = simulated(found, renderers, shape, ours, real, real_nc, align_real, region,
                                                         inside)
            moved["located"] = {"u_px": found.u, "v_px": found.v, "moved_px": [found.u - there.u, found.v - there.v],
                                "bound_px": LOCATE_BOUND_PX, "roll_deg": None if period is None else
                                math.degrees(found.roll_rad), "phong_change_corr": corr,
                                "strength_ratio": _by_renderer(found_scores, "strength_ratio"),
                                "shape_corr": _by_renderer(found_scores, "shape_corr"),
                                "strength": _by_renderer(found_scores, "strength"), **_factors(found_scores)}
            say(f"  located on the real tile at ({found.u:.0f}, {found.v:.0f}) px (phong's change correlates "
                f"{corr:.2f}): strength ratio {moved['located']['strength_ratio']}, shape corr "
                f"{moved['located']['shape_corr']}")
        out_tiles[k] = {
            "object": name,
            "object_from": "--object" if objects and k in objects else "caption",
            "depth_mm": c.depth_m * 1e3,
            "place": {"u_px": c.u, "v_px": c.v, "point_mm": (point * 1e3).tolist(), "normal": normal.tolist(),
                      "published_patch_u_px": rec.centroid[0], "published_patch_v_px": rec.centroid[1]},
            "roll_deg": None if period is None else math.degrees(c.roll_rad),
            "roll_period_deg": None if period is None else math.degrees(period),
            "match": {"field": MATCH_FIELD, "tile": match_path.name, "mse": rec.mse, "renders": rec.evaluations,
                      "alignment": rec.alignment.to_dict(),
                      **{key: {f: v[key] for f, v in fields.items()}
                         for key in ("mae", "no_contact_mae", "mae_contact", "no_contact_mae_contact")},
                      "by_field": fields},
            "strength_ratio": _by_renderer(scores, "strength_ratio"),
            "shape_corr": _by_renderer(scores, "shape_corr"),
            "strength": {"real": real_strength, **_by_renderer(scores, "strength")},
            **_factors(scores),
            "reference_noise": ({"passes": scores["pbr"].get("passes"), "contact_rse": scores["pbr"].get("contact_rse")}
                                if "pbr" in scores else None),
            "real": {"tile": col.real.name, "region_px": int(region.sum()), "alignment": align_real.to_dict(),
                     "patch_u_px": None if real_centre is None else real_centre[0],
                     "patch_v_px": None if real_centre is None else real_centre[1]},
            "at_real_place": moved,
            "images": figures or None,
            "seconds": {"recover": t_recover, **{f"render_{n}": v for n, v in seconds.items()},
                        "total": time.perf_counter() - t_col},
        }
    pbr_info = None
    if pbr_settings is not None:
        pbr_info = {"options": pbr_options, "effects": list(effects) or "defaults", "film": pbr_settings["film"],
                    "passes": [pbr_settings["min_passes"], pbr_settings["max_passes"]],
                    "target_rse": pbr_settings["target_rse"], "variant": pbr_settings["variant"]}
    out = {
        "tiles_dir": str(tiles_dir),
        "reference_dir": str(reference_dir),
        "columns": sorted(out_tiles),
        "tiles": out_tiles,
        "real_no_contact": how,
        "region": f"mean |real - no-contact| over channels > {CHANGE_LEVEL}, dilated by {REGION_DILATION} px, inside "
                  "the image circle less a px",
        "renderers": {"phong": {"options": {}, "field": "plane (the plugin's default)", "background": "none"},
                      "pbr": pbr_info},
        "seconds": time.perf_counter() - t_all,
        "stage_seconds": stage_seconds,
    }
    out = _clean(out)
    atomic_write_json(Path(json_path), out)
    return out


def parse_objects(items) -> dict[int, str]:
    """``--object K=NAME`` items as {K: NAME}; TileError naming a bad one."""
    out = {}
    for item in items or ():
        k, sep, name = str(item).partition("=")
        if not sep or not k.strip().isdigit() or not name.strip():
            raise TileError(f"--object must be K=NAME (a column number and an indenter), got {item!r}")
        out[int(k)] = name.strip()
    return out


def cmd_bench_tiles(args) -> int:
    out = run(args.json, args.tiles, objects=parse_objects(args.object), reference=not args.no_reference,
              photons=args.photons, quiet=args.quiet, effects=tuple(args.effects or ()), images_dir=args.images)
    keys = ("object", "depth_mm", "strength_ratio", "shape_corr")
    summary = {k: {key: t[key] for key in keys} for k, t in out["tiles"].items()}
    print(json.dumps(summary, indent=1))
    print(f"wrote {args.json}")
    return 0


def register(registry) -> None:
    from scenes.commands import add_quiet_argument

    p = registry.bench("tiles", cmd_bench_tiles, "recover the GelTip figure's contacts from the published "
                       "simulations and score the reference and the fast path on the real tiles")
    p.add_argument("--tiles", metavar="DIR", help="the tiles (default: the shared data's real_contacts, "
                                                  "../shared/data/geltip_reference/real_contacts)")
    p.add_argument("--object", action="append", metavar="K=NAME",
                   help="column K's object (default the caption's: " + ", ".join(
                       f"{k}={n}" for k, n in enumerate(CAPTION)) + ")")
    p.add_argument("--no-reference", action="store_true", help="the fast path only (no physically based reference)")
    p.add_argument("--photons", type=int, default=PHOTONS, metavar="N",
                   help=f"the reference's photons per pass (default {PHOTONS})")
    p.add_argument("--effects", action="append", metavar="NAME=V",
                   help="a reference effect (pbr_tactile.effects.Effects; repeatable; default: its defaults), e.g. "
                        "coating_albedo=0.4")
    p.add_argument("--images", metavar="DIR",
                   help="write each column's real and simulated changes side by side there (colK_recovered.png, "
                        "colK_at_real_place.png: real tile, its change, region, then per renderer its no-contact "
                        "tile and change through the real camera's exposure; grey is no change)")
    add_quiet_argument(p)
