"""The contact located on the real tile: the fast path's render moved until its change
correlates best with the real one's."""

from __future__ import annotations

import numpy as np
from scipy import optimize

from .frames import Alignment, change, to_tile
from .recovery import Contact
from .scoring import pearson

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
