"""Offline baking of per-LED light fields at every camera pixel, cached on disk.

A light field holds, per LED m and pixel, the unit direction in which the LED's light
travels when it arrives at the pixel's membrane point (camera frame). The renderer uses
L_m = -field.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import trimesh

from scenes.cache import cached, make_key
from scenes.camera import Camera, SurfaceSamples, cast_rays, reference_depth
from scenes.geometry import mesh_digest
from scenes.shapes.mesh import validate_mesh
from scenes.spec import LED

from .sources import FREE_SOURCE_TOLERANCE_M, LED_SNAP_TOLERANCE_M, Sources, snap_leds

METHODS = ("linear", "plane", "geodesic", "transport")

#: Bump when what ``bake`` stores changes (all methods' cache entries are rebuilt).
FORMAT_VERSION = 2


@dataclass(frozen=True)
class FieldMethod:
    """A light-field method's baker, from its module."""

    baker: Callable  # Baker(mesh), heavy set-up once; .bake(samples, sources) -> (L, K, 3) fields, (L, K) valid
    version: int  # the module's VERSION: bumping it rebuilds the method's cache entries
    free_sources: bool  # its light leaves each LED's own place (the module's FREE_SOURCES; False without)


# Each method's module is imported when the method is first used: geodesic and transport
# import libraries (pygeodesic, potpourri3d) that only they need.
def _linear() -> FieldMethod:
    from . import linear

    return FieldMethod(linear.LinearBaker, linear.VERSION, linear.FREE_SOURCES)


def _plane() -> FieldMethod:
    from . import plane

    return FieldMethod(plane.PlaneBaker, plane.VERSION, False)


def _geodesic() -> FieldMethod:
    from . import geodesic

    return FieldMethod(geodesic.GeodesicBaker, geodesic.VERSION, False)


def _transport() -> FieldMethod:
    from . import transport

    return FieldMethod(transport.TransportBaker, transport.VERSION, False)


_BAKERS: dict[str, Callable[[], FieldMethod]] = {
    "linear": _linear, "plane": _plane, "geodesic": _geodesic, "transport": _transport}


@dataclass(frozen=True)
class LightFields:
    """Baked fields of one method on one membrane, camera and LED set.

    fields : (L, H, W, 3) float32, unit propagation directions; zero where invalid.
    valid : (L, H, W) bool.
    depth : (H, W) float32, metres, the no-contact depth D_ref the fields were baked on.
    normals : (H, W, 3) float32, unit outward normals of the undeformed membrane.
    """

    method: str
    fields: np.ndarray
    valid: np.ndarray
    depth: np.ndarray
    normals: np.ndarray


def field_method(method: str) -> FieldMethod:
    """The baker of ``method`` (one of METHODS), its module imported on first use."""
    if method not in _BAKERS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    return _BAKERS[method]()


def make_baker(method: str, mesh: trimesh.Trimesh):
    """The stateful baker of a method (heavy set-up done once per mesh)."""
    return field_method(method).baker(mesh)


def bake_samples(
    method: str, mesh: trimesh.Trimesh, samples: SurfaceSamples, sources: Sources
) -> tuple[np.ndarray, np.ndarray]:
    """Bake one method at given surface samples: (L, K, 3) unit fields, (L, K) valid."""
    fields, valid = make_baker(method, mesh).bake(samples, sources)
    fields = np.asarray(fields, dtype=np.float64)
    valid = np.asarray(valid, dtype=bool) & np.isfinite(fields).all(axis=-1)
    fields[~valid] = 0.0
    return fields, valid


def bake(
    mesh: trimesh.Trimesh,
    camera: Camera,
    leds: tuple[LED, ...] | list[LED],
    method: str,
    *,
    use_cache: bool = True,
    timings: dict | None = None,
) -> LightFields:
    """Bake (or load from the cache) the light fields of one method.

    The cache key hashes the mesh, LEDs, camera, method and the method's VERSION, so any
    change rebuilds; a corrupt or stale cache file is detected and rebuilt.
    """
    baker = field_method(method)
    validate_mesh(mesh, "mesh")
    key = make_key(
        "fields", FORMAT_VERSION, mesh_digest(mesh), [dataclasses.asdict(led) for led in leds], dataclasses.asdict(camera), method,
        baker.version,
    )

    def build() -> dict[str, np.ndarray]:
        t0 = time.perf_counter()
        samples = cast_rays(mesh, camera)
        sources = snap_leds(mesh, leds, FREE_SOURCE_TOLERANCE_M if baker.free_sources else LED_SNAP_TOLERANCE_M)
        fields, valid = bake_samples(method, mesh, samples, sources)
        out = {
            "fields": np.stack([samples.scatter(f.astype(np.float32)) for f in fields]),
            "valid": np.stack([samples.scatter(v) for v in valid]),
            "depth": reference_depth(mesh, camera)[0],
            "normals": samples.scatter(samples.normals.astype(np.float32)),
        }
        if timings is not None:
            timings[method] = time.perf_counter() - t0
        return out

    arrays = cached(f"fields-{method}", key, build, use_cache=use_cache)
    expected = (len(leds),) + camera.shape + (3,)
    if arrays["fields"].shape != expected:
        raise ValueError(f"baked fields have shape {arrays['fields'].shape}, expected {expected}")
    return LightFields(method, arrays["fields"], arrays["valid"], arrays["depth"], arrays["normals"])


def bake_all(
    mesh: trimesh.Trimesh,
    camera: Camera,
    leds: tuple[LED, ...] | list[LED],
    methods=METHODS,
    desc: str = "baking light fields",
) -> tuple[dict[str, LightFields], dict[str, float]]:
    """Bake (or load) several methods with a progress bar.

    Returns {method: LightFields} and {method: seconds taken, cache hits included}.
    """
    from tqdm import tqdm

    out, seconds = {}, {}
    with tqdm(methods, desc=desc, unit="field") as bar:
        for method in bar:
            bar.set_postfix_str(method)
            t0 = time.perf_counter()
            out[method] = bake(mesh, camera, leds, method)
            seconds[method] = time.perf_counter() - t0
    return out, seconds
