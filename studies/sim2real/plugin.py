"""The fast path as a compact dataset renderer, for the learning study's large datasets.

It renders exactly as the ``phong`` plugin (``phong_reference.plugin``) and writes the
same 8-bit image, but keeps each contact's depth only as its *indentation* at a reduced
resolution, ``indentation/<id>.npy``: D_ref - D (metres, differences at or below the
contact threshold set to 0), averaged over ``depth_factor`` x ``depth_factor`` blocks,
which is what the gap diagnosis' fast model re-renders an effect from
(``studies.gap.model.FastModel.working_depth``). The full map is 1.2 MB of a 640x480
sample; the extended protocol's 23,040 taps would hold 28 GB of it.

The study passes this module to ``scenes.generate`` as the renderer (``datasets.ensure_sim``).
"""

from __future__ import annotations

import numpy as np

from phong_reference import plugin as phong
from scenes.camera import CONTACT_EPS_M
from scenes.images import block_mean

SOURCE = "sim"
#: The block size of the stored indentation, by default: 160x120 for a 640x480 camera.
DEPTH_FACTOR = 4


def _split(options: dict) -> tuple[dict, int]:
    options = dict(options)
    factor = options.pop("depth_factor", DEPTH_FACTOR)
    if isinstance(factor, bool) or not isinstance(factor, int) or factor < 1:
        raise ValueError(f"option depth_factor must be a positive integer, got {factor!r}")
    return options, factor


def indentation(depth: np.ndarray, ref_depth: np.ndarray, factor: int) -> np.ndarray:
    """(H / factor, W / factor) float32 block means of D_ref - D, metres, with differences
    at or below the contact threshold (``scenes.camera.CONTACT_EPS_M``) set to 0."""
    delta = np.asarray(ref_depth, np.float32) - np.asarray(depth, np.float32)
    delta[np.abs(delta) <= CONTACT_EPS_M] = 0.0
    return block_mean(delta, factor).astype(np.float32)


def prepare(spec, mesh, camera, options: dict) -> dict:
    opts, factor = _split(options)
    if camera.width % factor or camera.height % factor:
        raise ValueError(f"option depth_factor {factor} does not divide the camera's {camera.width}x{camera.height}")
    return {**phong.prepare(spec, mesh, camera, opts), "depth_factor": factor,
            "stored_depth": f"indentation/<id>.npy: D_ref - D in metres, block means of {factor}x{factor} px; "
                            "no full-resolution depth"}


class CompactRenderer:
    """The phong plugin's renderer whose sample keeps a reduced indentation map and no
    full-resolution depth (``writes_depth``)."""

    writes_depth = False

    def __init__(self, spec, mesh, camera, ref_depth, options: dict):
        opts, self.factor = _split(options)
        self._phong = phong.make_renderer(spec, mesh, camera, ref_depth, opts)
        self.ref_depth = self._phong.ref_depth

    @property
    def no_contact(self) -> np.ndarray:
        return self._phong.no_contact

    def render(self, depth: np.ndarray) -> np.ndarray:
        return self._phong.render(depth)

    def render_sample(self, depth: np.ndarray) -> dict:
        return {"image": self.render(depth),
                "arrays": {"indentation": indentation(depth, self.ref_depth, self.factor)}}


def make_renderer(spec, mesh, camera, ref_depth, options) -> CompactRenderer:
    return CompactRenderer(spec, mesh, camera, ref_depth, options)
