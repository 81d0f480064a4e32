"""Renderer plugins: what one offers (``RendererPlugin``), and the registry that finds one by name.

A renderer plugin turns the rig's depth maps into a dataset's images. The ones a user can
name are the entry points of the group ``tactile_sim.renderers`` (pyproject.toml:
``phong``, ``pbr``). Only the command-line layer looks a plugin up by name
(``get_renderer``) and passes it into the code below it (``scenes.generate``,
``rig.virtual``, the calibration, the studies), which runs whatever it is given and never
chooses a renderer; ``tests/test_imports.py`` checks that. This module imports no renderer.

A plugin is usually a module (``phong_reference.plugin``, ``pbr_tactile.plugin``) with

- ``SOURCE``: the dataset's ``source`` of its images (``scenes.dataset.SOURCES``);
- ``prepare(spec, mesh, camera, options) -> settings``, run once on the driver: validates
  the options, fills the caches, and returns the JSON settings that dataset.json records
  as ``renderer`` (by convention their ``"renderer"`` entry names the renderer);
- ``make_renderer(spec, mesh, camera, ref_depth, options)``, run once per worker process:
  a ``DatasetRenderer``.

**The contract.** A plugin renders with the spec, the mesh and the camera it is handed,
as they are: it never swaps in a camera of its own (``Camera.from_spec``), nor re-derives
the spec. A unit's profile (option ``profile``) is still applied by each plugin from its
options (``phong_reference.plugin.unit_spec``, ``pbr_tactile.plugin.unit_of``), in each
of ``prepare``, ``shared`` and ``make_renderer``, and then the unit's spec and camera are
the ones its renders use; applying it once, where the spec is resolved, and handing the
plugins the result is the contract's next step (issue 75). Tested:
``tests/test_renderers.py`` and ``tests/test_pbr_dataset.py`` hand each renderer a camera
whose image circle is not the spec's, and each draws that circle.

Optional parts are protocols of their own, so that ``isinstance`` says whether a plugin
offers one (a runtime-checkable protocol checks that the members are there, and not None):

- ``SharesInputs``: ``shared(spec, mesh, camera, options) -> picklable``, large inputs every
  worker needs (e.g. cached photon maps). The driver computes them once; each worker gets
  them as ``make_renderer(..., shared=value)`` (through Ray's object store on a cluster).
  A plugin without it is never given ``shared=``.
- ``Calibrates``: ``calibrate(spec, mesh, camera, profile, taps, background) -> (table,
  report)``, the fit of its constants to a unit's taps, which ``tactile-sim calibrate``
  writes into the profile (the fast path's).

A renderer (``DatasetRenderer``) has ``.render(depth) -> (H, W, 3) float image`` and
``.no_contact``; optionally ``.render_sample(depth) -> {"image": ..., "arrays": {name:
array}, "record": {field: value}}`` (``SampleRenderer``), whose arrays are written as
``<name>/<id>.npy`` and whose record fields join the sample's line; and ``writes_depth``
(``OwnDepth``): where it is False the renderer keeps its own (e.g. reduced) depth among
those arrays, and the full-resolution depth map is not written (it is 1.2 MB of a 640x480
sample).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from importlib import import_module
from importlib.metadata import EntryPoint, entry_points
from typing import Any, Protocol, runtime_checkable

import numpy as np

#: The entry point group of the renderers a user can name.
RENDERER_GROUP = "tactile_sim.renderers"
#: The members every renderer plugin has (``RendererPlugin``).
REQUIRED = ("SOURCE", "prepare", "make_renderer")


@runtime_checkable
class DatasetRenderer(Protocol):
    """Depth map -> tactile image, for one worker (a plugin's ``make_renderer``)."""

    #: (H, W, 3) float in [0, 1]: the image without contact.
    no_contact: np.ndarray

    def render(self, depth: np.ndarray) -> np.ndarray:
        """(H, W) float32 planar z-depth, metres -> (H, W, 3) float image in [0, 1]."""


@runtime_checkable
class SampleRenderer(Protocol):
    """Optional part of a ``DatasetRenderer``: a sample's image with extra arrays and record fields."""

    def render_sample(self, depth: np.ndarray) -> dict:
        """``{"image": (H, W, 3), "arrays": {name: array}, "record": {field: value}}``;
        ``arrays`` and ``record`` may be left out."""


@runtime_checkable
class OwnDepth(Protocol):
    """Optional part of a ``DatasetRenderer``: whether a sample's full depth map is written."""

    #: False: the renderer keeps its own depth among its arrays, and the map is not written.
    writes_depth: bool


@runtime_checkable
class RendererPlugin(Protocol):
    """What every renderer plugin offers (the module doc); a module can be one."""

    #: The dataset's ``source`` of its images (``scenes.dataset.SOURCES``), e.g. "sim".
    SOURCE: str

    def prepare(self, spec, mesh, camera, options: dict) -> dict:
        """Validate ``options``, fill the caches (once, on the driver); the JSON settings."""

    def make_renderer(self, spec, mesh, camera, ref_depth: np.ndarray, options: dict) -> DatasetRenderer:
        """The renderer of one worker against the no-contact depth ``ref_depth`` (H, W), metres."""


@runtime_checkable
class SharesInputs(Protocol):
    """Optional part of a plugin: inputs computed once on the driver for every worker.

    Its ``make_renderer`` takes them as ``shared=`` (None: it computes them itself).
    """

    def shared(self, spec, mesh, camera, options: dict) -> Any:
        """Picklable inputs every worker's ``make_renderer(..., shared=value)`` needs."""


@runtime_checkable
class Calibrates(Protocol):
    """Optional part of a plugin: the fit of its constants to a unit's taps."""

    def calibrate(self, spec, mesh, camera, profile, taps, background: np.ndarray) -> tuple[dict, dict]:
        """(entries of the profile's table for this renderer, the report)."""


def check_plugin(plugin: Any, name: str = "renderer") -> RendererPlugin:
    """``plugin`` if it is a ``RendererPlugin``, else a ValueError naming what it lacks."""
    if isinstance(plugin, RendererPlugin):
        return plugin
    if isinstance(plugin, str):
        raise ValueError(f"{name} must be a renderer plugin (scenes.renderers.RendererPlugin), got the name "
                         f"{plugin!r}; the command line looks one up by name (scenes.renderers.get_renderer)")
    missing = [member for member in REQUIRED if getattr(plugin, member, None) is None]
    raise ValueError(f"{name} must be a renderer plugin (scenes.renderers.RendererPlugin: {', '.join(REQUIRED)}), "
                     f"got {plugin_name(plugin)}, which lacks {', '.join(missing)}")


def plugin_name(plugin: Any) -> str:
    """A plugin's name for messages: its module's import path, else its type's name."""
    return getattr(plugin, "__name__", None) or type(plugin).__name__


@functools.cache
def _entry_points() -> dict[str, EntryPoint]:
    return {ep.name: ep for ep in entry_points(group=RENDERER_GROUP)}


def renderers() -> tuple[str, ...]:
    """The names of the registered renderer plugins, sorted (entry points read once)."""
    return tuple(sorted(_entry_points()))


def get_renderer(name: str) -> RendererPlugin:
    """The renderer plugin called ``name`` in the registry, or, for a name with a dot, the
    plugin module of that import path (one not registered: a test's, a study's own).

    For the command-line layer only (the module doc).
    """
    found = _entry_points()
    if name in found:
        plugin = found[name].load()
    elif "." in name:
        try:
            plugin = import_module(name)
        except ImportError as exc:
            raise ValueError(f"renderer {name!r} is not an importable module: {exc}") from None
    else:
        raise ValueError(f"renderer must be one of {list(renderers())} or an importable module path "
                         f"'package.module', got {name!r}")
    return check_plugin(plugin, f"renderer {name!r}")


def build_renderer(make_renderer: Callable[..., DatasetRenderer], spec, mesh, camera, ref_depth: np.ndarray,
                   options: dict, shared: Any = None) -> DatasetRenderer:
    """``make_renderer(spec, mesh, camera, ref_depth, options)`` (a plugin's), given
    ``shared=`` only where there is a value: a plugin that is no ``SharesInputs`` takes
    none, and one that is computes its own when given None."""
    args = (spec, mesh, camera, ref_depth, options)
    return make_renderer(*args) if shared is None else make_renderer(*args, shared=shared)


#: Renderer options of the dataset command, by option key: the argument holding each.
#: phong takes field, background, rectify and elastic; pbr the others (see its plugin).
RENDERER_OPTIONS = {
    "field": "field", "background": "background", "rectify": "rectify", "elastic": "elastic",
    "target_rse": "target_rse", "max_passes": "max_passes", "effects": "effect", "estimator": "estimator", "inscatter": "inscatter",
    "photons": "photons", "camera_spp": "camera_spp", "kernel_radius_mm": "kernel_radius_mm",
    "no_contact_runs": "no_contact_runs", "film": "film", "profile": "profile", "seed": "render_seed",
}
