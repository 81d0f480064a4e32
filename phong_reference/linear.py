"""Linear light field: light travels in straight lines from each LED."""

from __future__ import annotations

import numpy as np

from scenes.camera import SurfaceSamples

from .sources import Sources

#: Bump when the method changes, so cached fields are rebuilt.
VERSION = 1
#: The light leaves the LED's own place, which need not lie on the membrane.
FREE_SOURCES = True


class LinearBaker:
    """Direction of the straight ray from the LED position to each surface point."""

    def __init__(self, mesh):
        self.mesh = mesh

    def bake(self, samples: SurfaceSamples, sources: Sources) -> tuple[np.ndarray, np.ndarray]:
        """Returns fields (L, K, 3) unit propagation directions and valid (L, K) bool."""
        d = samples.points[None, :, :] - sources.positions[:, None, :]
        n = np.linalg.norm(d, axis=-1, keepdims=True)
        valid = n[..., 0] > 0
        return np.divide(d, n, out=np.zeros_like(d), where=n > 0), valid


def bake_linear(mesh, samples: SurfaceSamples, sources: Sources):
    return LinearBaker(mesh).bake(samples, sources)
