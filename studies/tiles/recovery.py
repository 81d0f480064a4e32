"""Recovery of a tap from a published tile: its place, depth and roll, searched on renders."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage, optimize

from .disk import TileError
from .frames import CHANGE_LEVEL, Alignment, align, change, changed_region, inner, largest_patch, tile_inside, to_tile
from .paper import published

#: Objects a roll about the normal does not change (searched without roll).
ROUND = ("sphere", "cylinder", "open_cylinder", "cone")
#: Roll symmetry period of objects that are not round, radians (a full turn otherwise).
ROLL_PERIOD_RAD = {"indented_prism": math.pi / 2}
#: The contact's patch is looked for this far (tile px) inside the image circle.
CIRCLE_MARGIN_PX = 3
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
