"""The no-contact control variate: a contact's photon map as the sensor's cached
no-contact map plus the change the contact makes, estimated with common random numbers.

A contact changes the membrane only locally, so with the same random numbers a
contact's photons walk exactly as the no-contact frame's do until they meet the dent.
The map of a pass,

    E_hat = G + (E_c - E_0),

takes E_c and E_0 from the same seed (E_c in the contact scene, E_0 in the undeformed
one) and G from ``runs`` further no-contact runs of independent seeds. E[E_0] = E[G], so
E_hat is unbiased for E_c's expectation; its variance is that of the difference plus
var(E_0) / runs. Each pass has its own G, so the spread across passes still measures
the whole error.

Measured on the GelTip with a 4 mm sphere pressed 1.5 mm (2^19 photons per LED, weight
window on): at the dent's vertices the difference's variance was 0.30 of E_c's, far
from it 0.02. With runs = 4 the pass maps' variance was 0.67 of the plain estimate's at
the dent and 0.30 far from it: far from the contact the gain is about ``runs``-fold,
at the contact G's share limits it.

E_0 and G depend only on the sensor, the effects, the photon count and the seed, not on
the contact, so they are cached on disk (``scenes.cache``, one entry for E_0 and one for
G per pass, float32 as traced): the first contact of a sensor pays for them, every later
one traces only its own photons. A memo (a plain dict by cache key) sits in front of the
disk cache: filled by one render, it carries the deposits to workers with no shared disk.

With a fluence grid (``pbr_tactile.fluence``), each run also carries the photons' tracks
in the elastomer, and a pass's fluence is combined the same way: phi_G + (phi_c - phi_0).
The grid is part of the key, so deposits without tracks keep their entries.
"""

from __future__ import annotations

import numpy as np

#: Bump when the photon tracer changes what it deposits: stale cache entries then miss.
CACHE_VERSION = 2
#: Default no-contact runs per pass that make G.
DEFAULT_RUNS = 8


def scene_fingerprint(mi, scene) -> list:
    """Everything in a loaded scene the light pass depends on, as hashable parts: each
    shape's id and bounds, each mesh's buffers, each smooth interface's IOR."""
    parts: list = []
    for shape in sorted(scene.shapes(), key=lambda s: s.id()):
        bbox = shape.bbox()
        parts.append([shape.id(), list(bbox.min), list(bbox.max)])
        if shape.is_mesh():
            parts.append(np.asarray(shape.vertex_positions_buffer()))
            parts.append(np.asarray(shape.faces_buffer()))
        params = mi.traverse(shape.bsdf())
        if "eta" in params:
            parts.append(float(params["eta"]))
    return parts


class NoContact:
    """Cached no-contact photon deposits of one undeformed scene (see module doc)."""

    def __init__(self, mi, scene, key_parts: list, runs: int = DEFAULT_RUNS, use_cache: bool = True,
                 memo: dict | None = None, grid=None):
        """key_parts: what else than the scene the deposits depend on (sources, medium,
        photons per run). memo: a dict of deposit arrays by cache key, read before the
        disk cache and given every array this object returns (None: none). grid: the
        undeformed scene's ``FluenceGrid``: each run's tracks are kept too."""
        from scenes.cache import make_key

        if runs < 1:
            raise ValueError(f"no-contact runs must be >= 1, got {runs}")
        self.runs = runs
        self._use_cache = use_cache
        self._memo = memo
        grid_parts = [] if grid is None else ["fluence", grid.origin, grid.voxel, grid.volume]
        self._base = make_key(CACHE_VERSION, mi.variant(), *scene_fingerprint(mi, scene), *key_parts, *grid_parts)

    def flux(self, name, trace, parts: tuple[str, ...] = ("flux",)) -> dict[str, np.ndarray]:
        """The no-contact deposits called ``name`` (JSON-able: a seed, with what the
        run is for), from the memo, the cache, or ``trace()`` stored: a dict of float32
        arrays named ``parts`` ("flux", (S, V); "track", (S, N) with a grid), which
        ``trace`` returns in that order (one array where parts is ("flux",))."""
        from scenes.cache import cached, make_key

        key = make_key(self._base, name)
        keys = {part: key if part == "flux" else make_key(key, part) for part in parts}
        if self._memo is not None and all(k in self._memo for k in keys.values()):
            return {part: self._memo[k] for part, k in keys.items()}

        def build():
            traced = trace()
            traced = (traced,) if len(parts) == 1 else traced
            return {part: np.asarray(a, np.float32) for part, a in zip(parts, traced, strict=True)}

        arrays = cached("pbr-nocontact", key if parts == ("flux",) else make_key(key, *parts), build,
                        use_cache=self._use_cache)
        if self._memo is not None:
            self._memo.update({k: arrays[part] for part, k in keys.items()})
        return {part: arrays[part] for part in parts}

    def pass_flux(self, seed: int, window_seed: int, trace, parts: tuple[str, ...] = ("flux",)
                  ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        """(E_0's deposits, G's deposits) for the pass of this seed, as ``flux`` returns
        them: the same seed as the contact's photons, and the mean of ``runs``
        independent seeds. trace(seed) traces one run, in the weight window of the pilot
        of ``window_seed`` (the key names the pilot, not the window's values, whose last
        bits vary from run to run with the order of Dr.Jit's atomic adds)."""
        from .streams import sampler_seed

        same = self.flux([int(seed), int(window_seed)], lambda: trace(seed), parts)

        def mean_of_runs():
            runs = [trace(sampler_seed(seed, run, 0xC0A7)) for run in range(self.runs)]
            if len(parts) == 1:
                return np.mean(runs, axis=0)
            return tuple(np.mean([run[i] for run in runs], axis=0) for i in range(len(parts)))

        return same, self.flux(["G", int(seed), int(window_seed), self.runs], mean_of_runs, parts)
