"""Benchmarks of the fast path: rendering speed against the published model, and baking."""

from __future__ import annotations

import os
import platform
import time
from pathlib import Path

import numpy as np
import trimesh
from scipy import ndimage

from scenes.camera import Camera
from scenes.contact import press
from scenes.geometry import membrane_mesh
from scenes.spec import SensorSpec

from .background import make_background
from .bake import METHODS, bake
from .render import Renderer, render


def published_frame(
    depth: np.ndarray,
    bkg_depth: np.ndarray,
    fields: list[np.ndarray],
    background: np.ndarray,
    leds,
    ambient: float,
    shininess: float,
    f: float,
    mask: np.ndarray,
) -> np.ndarray:
    """A plain numpy transcription of the published per-frame model (the baseline).

    Whole frame, float64, as the published code: Gaussian 55x55 smoothing, point cloud
    from a fresh pixel grid, Sobel normals, and per-light Phong with R formed explicitly.
    """
    h, w = depth.shape
    diff = bkg_depth - depth
    blurred = ndimage.gaussian_filter(diff, 5.0, truncate=27 / 5.0, mode="mirror")
    d = np.minimum(depth, bkg_depth - blurred)
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    cloud = np.stack([(u - (w - 1) / 2) * d / f, (v - (h - 1) / 2) * d / f, d], axis=-1)
    dx = np.stack([ndimage.sobel(cloud[..., c], axis=1) for c in range(3)], axis=-1)
    dy = np.stack([ndimage.sobel(cloud[..., c], axis=0) for c in range(3)], axis=-1)
    n = np.cross(dx, dy)
    n = n / np.linalg.norm(n, axis=-1, keepdims=True)
    n = n * -np.sign(np.sum(n * cloud, axis=-1, keepdims=True))
    view = -cloud / np.linalg.norm(cloud, axis=-1, keepdims=True)
    out = ambient * background
    for field, led in zip(fields, leds):
        lm = -field
        dot = np.clip(np.sum(lm * n, axis=-1), 0, None)
        r = 2 * dot[..., None] * n - lm
        rv = np.sum(r * view, axis=-1)
        out = out + (led.k_d * dot + led.k_s * rv**shininess)[..., None] * np.asarray(led.colour)
    return np.clip(out, 0, 1) * mask[..., None]


def contact_frames(spec: SensorSpec, camera: Camera, mesh, ref_depth, count: int, rng: np.random.Generator):
    """Realistic contacts for timing: spheres and boxes pressed 0.5-2 mm at random pixels."""
    frames = []
    radius = camera.mask_radius_px * 0.85
    while len(frames) < count:
        a, r = rng.uniform(0, 2 * np.pi), radius * np.sqrt(rng.uniform())
        pixel = (camera.cx + r * np.cos(a), camera.cy + r * np.sin(a))
        if len(frames) % 2 == 0:
            shape = trimesh.primitives.Sphere(radius=rng.uniform(0.002, 0.006))
        else:
            shape = trimesh.creation.box(rng.uniform(0.002, 0.008, size=3))
        depth = press(ref_depth, camera, mesh, shape, pixel, rng.uniform(0.0005, 0.002), rng.uniform(0, np.pi))
        if np.any(depth < ref_depth):
            frames.append(depth)
    return frames


def _median_ms(fn, frames, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        for frame in frames:
            t0 = time.perf_counter()
            fn(frame)
            times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e3)


def bench_phong(spec: SensorSpec, frames: int = 16, repeats: int = 3, seed: int = 0) -> dict:
    """Time the fast path against the published model on the same frames, same run."""
    camera = Camera.from_spec(spec)
    mesh = membrane_mesh(spec)
    fields = bake(mesh, camera, spec.leds, "linear")
    background = make_background("solid", camera)
    renderer = Renderer.from_fields(spec, camera, fields, background)
    depths = contact_frames(spec, camera, mesh, fields.depth, frames, np.random.default_rng(seed))
    field_list = [f.astype(np.float64) for f in fields.fields]
    ref64 = fields.depth.astype(np.float64)

    def baseline(d):
        return published_frame(
            d.astype(np.float64), ref64, field_list, background.astype(np.float64), spec.leds,
            spec.material.ambient, spec.material.shininess, camera.f, camera.mask,
        )

    def full(d):
        return render(d, renderer.ref_depth, camera, spec, renderer.L, background)

    # Warm up every path once (page faults, caches), then interleave the measurements.
    for fn in (renderer.render, full, baseline):
        fn(depths[0])
    fast_ms = _median_ms(renderer.render, depths, repeats)
    full_ms = _median_ms(full, depths, repeats)
    base_ms = _median_ms(baseline, depths, max(1, repeats // 3))
    fast_ms_again = _median_ms(renderer.render, depths, repeats)
    return {
        "ms_per_frame_median": min(fast_ms, fast_ms_again),
        "baseline_ms_per_frame_median": base_ms,
        "speedup": base_ms / min(fast_ms, fast_ms_again),
        "full_frame_ms_per_frame_median": full_ms,
        "full_frame_speedup": base_ms / full_ms,
        "fast_ms_first_and_second_pass": [fast_ms, fast_ms_again],
        "frames": len(depths),
        "repeats": repeats,
        "resolution": [camera.width, camera.height],
        "leds": len(spec.leds),
        "contacts": "spheres r 2-6 mm and boxes 2-8 mm pressed 0.5-2 mm at random pixels (seeded)",
        "method": "Renderer (contact window) vs render (whole frame, same chain) vs published_frame "
        "(numpy transcription of the published model), medians over the same frames in one process",
        **_machine(),
    }


def bench_bake(spec: SensorSpec, methods=METHODS) -> dict:
    """Cold-cache bake time of every method at the spec camera's resolution."""
    camera = Camera.from_spec(spec)
    mesh = membrane_mesh(spec)
    seconds: dict[str, float] = {}
    for method in methods:
        t0 = time.perf_counter()
        bake(mesh, camera, spec.leds, method, use_cache=False)
        seconds[method] = time.perf_counter() - t0
    return {
        "seconds": seconds,
        "seconds_total": float(sum(seconds.values())),
        "vertices": int(len(mesh.vertices)),
        "faces": int(len(mesh.faces)),
        "pixels": int(camera.width * camera.height),
        "pixels_in_mask": int(camera.mask.sum()),
        "resolution": [camera.width, camera.height],
        "cache": "cold (use_cache=False); each includes ray casting the pixels",
        **_machine(),
    }


def _machine() -> dict:
    return {"cpus": os.cpu_count(), "python": platform.python_version(), "machine": platform.machine()}


def write_json(path: str | Path, results: dict) -> Path:
    from scenes.dataset import atomic_write_json

    atomic_write_json(Path(path), results)
    return Path(path)
