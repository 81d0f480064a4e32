"""Tiles and frames: where a tile lies in the frame, a frame image brought to a tile, and
where a tile changes."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage, optimize

#: An alignment's scale (frame px per tile px) stays within this share of the frame's
#: height over the tile's (the figure's tiles show the frame's height: measured 2.817-2.821
#: on the 171-173 px tiles, whose height gives 2.775-2.807).
SCALE_SLACK = 0.08
#: An alignment's offsets stay this close to the centred crop's, frame px.
SHIFT_BOUND_PX = 12.0
#: Tile px at each edge left out of every comparison (the figure's white gaps).
BORDER_PX = 3
#: A tile pixel whose mean |difference| over channels exceeds this shows the contact (README).
CHANGE_LEVEL = 0.05
#: Changed pixels this close (tile px) are one patch of a contact.
PATCH_GAP_PX = 2
#: Nelder-Mead's budget per alignment (evaluations).
ALIGN_EVALUATIONS = 200


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


def tile_inside(shape: tuple[int, int], alignment: Alignment, camera, margin_px: int = 1) -> np.ndarray:
    """(h, w) bool: a tile's inner pixels inside the camera's image circle, less
    ``margin_px`` tile px."""
    circle = sample(camera.mask.astype(np.float64), shape, alignment) > 0.999
    return ndimage.binary_erosion(circle, iterations=margin_px) & inner(shape)
