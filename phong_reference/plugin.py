"""The fast path as a dataset renderer plugin (entry point ``tactile_sim.renderers``)."""

from __future__ import annotations

import dataclasses

import numpy as np

from scenes.camera import CONTACT_EPS_M, Camera
from scenes.elastic import MembraneLayer, check_model
from scenes.spec import SensorSpec

from .background import make_background
from .bake import METHODS, bake
from .render import Renderer, light_vectors

#: The options this renderer takes.
OPTIONS = ("field", "background", "rectify", "elastic")


def options_from(options: dict) -> dict:
    unknown = sorted(set(options) - set(OPTIONS))
    if unknown:
        raise ValueError(f"the phong renderer takes no option {', '.join(unknown)}; its options are "
                         f"{', '.join(OPTIONS)}")
    field = options.get("field", "plane")
    if field not in METHODS:
        raise ValueError(f"field must be one of {METHODS}, got {field!r}")
    background = str(options.get("background", "none"))
    # The published smoothing, or the layer model: the surface the reference renders.
    elastic = check_model(options.get("elastic", "published"), "elastic")
    return {"field": field, "background": background, "rectify": bool(options.get("rectify", False)),
            "elastic_model": elastic}


def prepare(spec: SensorSpec, mesh, camera: Camera, options: dict) -> dict:
    """Bake what the renderer needs (cached on disk) and return its settings."""
    opts = options_from(options)
    bake(mesh, camera, spec.leds, opts["field"])
    make_background(opts["background"], camera)  # fail early on a bad image
    return {"renderer": "phong", **opts, "elastic": dataclasses.asdict(spec.elastic)}


class PhongDatasetRenderer:
    """Depth map -> tactile image with the fast path, for dataset generation."""

    def __init__(self, spec: SensorSpec, mesh, camera: Camera, ref_depth: np.ndarray, options: dict):
        opts = options_from(options)
        fields = bake(mesh, camera, spec.leds, opts["field"])
        layer = MembraneLayer(mesh, spec, camera) if opts["elastic_model"] == "layer" else None
        self._renderer = Renderer(
            spec, camera, ref_depth, light_vectors(fields, opts["rectify"]), make_background(opts["background"], camera),
            layer,
        )
        self.ref_depth = self._renderer.ref_depth

    @property
    def no_contact(self) -> np.ndarray:
        return self._renderer.base

    def render(self, depth: np.ndarray) -> np.ndarray:
        depth = np.asarray(depth, dtype=np.float32)
        depth = np.where(np.abs(depth - self.ref_depth) <= CONTACT_EPS_M, self.ref_depth, depth)
        return self._renderer.render(depth)


def make_renderer(spec, mesh, camera, ref_depth, options) -> PhongDatasetRenderer:
    return PhongDatasetRenderer(spec, mesh, camera, ref_depth, options)
