"""Benchmark of the reference: time to 2 % relative standard error, photons vs volpath."""

from __future__ import annotations

import os
import tempfile
import time
from unittest import mock

import numpy as np
import trimesh

from scenes.camera import CONTACT_EPS_M, Camera, reference_depth
from scenes.contact import press
from scenes.geometry import membrane_mesh
from scenes.spec import SensorSpec

from .effects import Effects
from .estimate import contact_rse
from .membrane import ElastomerBuilder
from .fluence import INSCATTER
from .render import KERNEL_RADIUS_M, render, render_photons
from .scene import geltip_scene, led_sources, write_meshes

#: The goal's noise level: relative standard error averaged over the contact region.
TARGET_RSE = 0.02


def bench_pbr(spec: SensorSpec, width: int = 320, height: int = 240, photons: int = 1 << 20,
              camera_spp: int = 16, volpath_spp: int = 16, passes: int = 2, seed: int = 0,
              kernel_radius: float = KERNEL_RADIUS_M, no_contact_runs: int = 0, cache: str | None = None) -> dict:
    """Time the estimators on one contact and extrapolate each to TARGET_RSE.

    Monte Carlo error falls as 1/sqrt(work), so time_to_target = T (rse / target)^2,
    with T and rse measured in the same run. Both figures are extrapolations, stated so.
    The photon estimator is timed with each way of finding the in-scattered light
    (``render.INSCATTER``: the old split and the fluence lookup), one after the other in
    this run. With no_contact_runs, the same contact is also timed with the no-contact
    control variate (pbr_tactile.nocontact), its cache in ``cache`` (default: a fresh
    folder, so the cold first contact is measured too).
    """
    camera = Camera.from_spec(spec)
    mesh = membrane_mesh(spec)
    ref, _ = reference_depth(mesh, camera)
    depth = press(ref, camera, mesh, trimesh.primitives.Sphere(radius=0.004), (camera.cx + 30, camera.cy - 20), 0.0015)
    rows = (np.arange(height) * camera.height / height).astype(int)
    cols = (np.arange(width) * camera.width / width).astype(int)
    region = (ref - depth)[np.ix_(rows, cols)] > CONTACT_EPS_M
    effects = Effects()
    build = ElastomerBuilder(mesh, spec, camera)
    t0 = time.perf_counter()
    grids = (build.grid(depth, ref), build.grid())
    t_grids = time.perf_counter() - t0
    with tempfile.TemporaryDirectory(prefix="tactile-bench-") as folder:
        wall = spec.membrane.glass_wall
        scene = geltip_scene(write_meshes(build(depth, ref), folder, wall), spec, camera, effects, width, height,
                             spp=4, seed=seed)
        # As pbr_tactile.render.reference does: the undeformed membrane sets the window.
        pilot_scene = geltip_scene(write_meshes(build(), f"{folder}/undeformed", wall), spec, camera, effects, width,
                                   height, spp=4, seed=seed)

        def run(runs: int, inscatter: str):
            t0 = time.perf_counter()
            est = render_photons(scene, led_sources(spec, effects), effects, photons=photons, spp=camera_spp,
                                 passes=passes, seed=seed, kernel_radius=kernel_radius, pilot_scene=pilot_scene,
                                 no_contact_runs=runs, fluence_grids=grids if inscatter == "fluence" else None)
            return est, time.perf_counter() - t0

        def timed(inscatter: str) -> dict:
            est, seconds = run(0, inscatter)
            rse = contact_rse(est, region)
            out = {"seconds_to_2pct": seconds * (rse / TARGET_RSE) ** 2, "seconds": seconds, "contact_rse": rse,
                   "median_rse_whole_image": float(np.nanmedian(est.relative_error[est.mean > 0])),
                   "no_contact_cache": None}
            if no_contact_runs:
                # A contact whose sensor's no-contact runs are cached (every contact after a
                # sensor's first): one run fills the cache, the next is timed.
                from scenes.cache import CACHE_ENV

                with mock.patch.dict(os.environ, {CACHE_ENV: cache or os.path.join(folder, "cache")}):
                    _, t_first = run(no_contact_runs, inscatter)
                    cached, t_cached = run(no_contact_runs, inscatter)
                rse_c = contact_rse(cached, region)
                out["no_contact_cache"] = {
                    "no_contact_runs": no_contact_runs, "seconds": t_cached, "contact_rse": rse_c,
                    "seconds_to_2pct": t_cached * (rse_c / TARGET_RSE) ** 2,
                    "median_rse_whole_image": float(np.nanmedian(cached.relative_error[cached.mean > 0])),
                    "cold_seconds": t_first}
            return out

        photon_runs = {inscatter: timed(inscatter) for inscatter in INSCATTER}
        t0 = time.perf_counter()
        vol = render(scene, spp=volpath_spp, passes=passes, seed=seed)
        t_volpath = time.perf_counter() - t0
        import mitsuba as mi

        variant = mi.variant()
    rse_v = contact_rse(vol, region)
    old, new = photon_runs["split"], photon_runs["fluence"]
    results = {
        "seconds_to_2pct": old["seconds_to_2pct"],
        "fluence_seconds_to_2pct": new["seconds_to_2pct"],
        "volpath_seconds_to_2pct": t_volpath * (rse_v / TARGET_RSE) ** 2,
        "resolution": [width, height],
        "variant": variant,
        "measured": {
            **{f"photons_{name}": {**run_, "photons_per_led_per_pass": photons, "passes": passes,
                                   "camera_spp_per_pass": camera_spp, "kernel_radius_m": kernel_radius,
                                   "inscatter": name, "includes": "scene load, pilot pass, density kernel, all passes"}
               for name, run_ in photon_runs.items()},
            "volpath": {"seconds": t_volpath, "contact_rse": rse_v, "spp": volpath_spp, "passes": passes},
            "fluence_grids_seconds": t_grids,
        },
        "contact_pixels": int(region.sum()),
        "method": "each extrapolated from one measured run by time x (rse / 0.02)^2 (error ~ 1/sqrt(work)); "
        "rse = root of the mean over the contact region of per-pixel variance / mean^2 (RMS relative "
        "standard error; the variance across passes is unbiased, its square root is not); the photon estimator "
        "with inscatter split (the old one) and fluence (pbr_tactile.fluence), one after the other in this run; "
        "no_contact_cache: the same render with pbr_tactile.nocontact's control variate, timed with the sensor's "
        "no-contact runs cached (cold_seconds: the first contact, which fills the cache); fluence_grids_seconds: "
        "the contact's and the undeformed solid's voxel grids (the undeformed one read from the disk cache "
        "when a run before measured it), outside every timed render",
        "cpus": os.cpu_count(),
    }
    results["speedup"] = results["volpath_seconds_to_2pct"] / results["seconds_to_2pct"]
    results["fluence_speedup"] = old["seconds_to_2pct"] / new["seconds_to_2pct"]
    if no_contact_runs:
        results["fluence_speedup_cached"] = (old["no_contact_cache"]["seconds_to_2pct"]
                                             / new["no_contact_cache"]["seconds_to_2pct"])
    return results
