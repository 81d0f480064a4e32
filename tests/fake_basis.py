"""Re-weighted variants for a stand-in of the reference's per-source basis
(``pbr_tactile.basis.emitter_basis``), for tests that replace the render with arrays or
formulas: each variant is the stand-in itself at the variant's effects, as if traced
there, so a grid re-weighted from one point (``basis.grid_bases``) sees what tracing each
point would have given."""

from __future__ import annotations

import dataclasses

import numpy as np

from pbr_tactile.reweight import PARAMETERS


def each_variant_traced(basis_at):
    """``basis_at(spec, mesh, camera, effects, *args, **kwargs)`` -> dict, extended to take
    ``perturb`` (K, 3) as ``emitter_basis`` does: ``variant_mean``, ``variant_variance``,
    ``ess_ratio`` 1 and ``valid``."""

    def basis(spec, mesh, camera, effects, *args, perturb=None, **kwargs):
        out = dict(basis_at(spec, mesh, camera, effects, *args, **kwargs))
        if perturb is None:
            return out
        values = np.asarray(perturb, np.float64)
        each = [basis_at(spec, mesh, camera, dataclasses.replace(effects, **dict(zip(PARAMETERS, map(float, row)))),
                         *args, **kwargs) for row in values]
        sources = out["mean"].shape[-1]
        return {**out, "perturb": values, "variant_mean": np.stack([e["mean"] for e in each]),
                "variant_variance": np.stack([e["variance"] for e in each]),
                "ess_ratio": np.ones((len(values), sources)), "valid": np.ones(len(values), bool)}

    return basis
