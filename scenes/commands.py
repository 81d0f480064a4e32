"""Subcommands of the scenes package: the MuJoCo rig (scene), datasets, and their bench."""

from __future__ import annotations

import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np

from .elastic import MODELS
from .spec import load_spec


def _objects(value: str) -> tuple[str, ...]:
    from .indenters import INDENTERS

    if value == "all":
        return INDENTERS
    names = tuple(n.strip() for n in value.split(",") if n.strip())
    if not names:
        raise ValueError("--objects must be 'all' or a comma-separated list of indenter names or STL paths")
    return names


def make_protocol(name: str, spec, mesh, objects, seed: int = 0):
    from .protocol import base_protocol, extended_protocol

    if name == "base":
        return base_protocol(spec, mesh, objects)
    if name == "extended":
        return extended_protocol(spec, mesh, objects, seed=seed)
    raise ValueError(f"protocol must be 'base' or 'extended', got {name!r}")


def _rig(args, tap_index: int | None = 0):
    from .geometry import membrane_mesh
    from .indenters import indenter
    from .rig import Rig, rig_scene

    spec = load_spec(args.spec)
    mesh = membrane_mesh(spec)
    name = args.object
    rig = Rig(rig_scene(spec, {name: indenter(name)}, membrane=mesh), spec)
    if tap_index is not None:
        protocol = make_protocol("base", spec, mesh, (name,))
        rig.press(protocol.taps[tap_index % len(protocol.taps)])
    return rig


def cmd_scene(args) -> int:
    if args.action == "export":
        from .geometry import membrane_mesh
        from .indenters import indenter
        from .rig import rig_scene

        spec = load_spec(args.spec)
        objects = _objects(args.object)
        scene = rig_scene(spec, {name: indenter(name) for name in objects}, membrane=membrane_mesh(spec))
        path = scene.export(args.output)
        print(f"wrote {path}; open it with: python -m mujoco.viewer --mjcf {path}")
        return 0
    if args.action == "snapshot":
        from .images import write_rgb

        rig = _rig(args, args.tap)
        write_rgb(args.output, rig.snapshot(args.width, args.height))
        rig.close()
        print(f"wrote {args.output}")
        return 0
    if args.action == "view":
        if not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY"):
            raise ValueError("scene view needs a display (DISPLAY is unset); use 'scene snapshot -o PNG' headless")
        os.environ.setdefault("MUJOCO_GL", "glfw")
        import mujoco.viewer

        rig = _rig(args, args.tap)
        mujoco.viewer.launch(rig.model, rig.data)
        return 0
    raise ValueError(f"unknown scene action {args.action!r}")


#: Renderer options of the dataset command, by option key: the argument holding each.
#: phong takes field, background, rectify and elastic; pbr the others (see its plugin).
RENDERER_OPTIONS = {
    "field": "field", "background": "background", "rectify": "rectify", "elastic": "elastic",
    "target_rse": "target_rse", "max_passes": "max_passes", "effects": "effect", "estimator": "estimator",
    "photons": "photons", "camera_spp": "camera_spp", "kernel_radius_mm": "kernel_radius_mm",
    "no_contact_runs": "no_contact_runs", "film": "film",
}


def _film_size(value: str) -> list[int]:
    """``WxH`` in pixels -> [W, H], for ``--film``."""
    import argparse

    try:
        width, height = (int(x) for x in value.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WxH in pixels, e.g. 320x240; got {value!r}") from None
    return [width, height]


def cmd_dataset(args) -> int:
    from .generate import generate
    from .geometry import membrane_mesh

    spec = load_spec(args.spec)
    protocol = make_protocol(args.protocol, spec, membrane_mesh(spec), _objects(args.objects), seed=args.seed)
    if args.limit:
        from dataclasses import replace

        protocol = replace(protocol, taps=protocol.taps[: args.limit])
    # Only the options given: each renderer refuses those it does not take.
    options = {key: getattr(args, attr) for key, attr in RENDERER_OPTIONS.items() if getattr(args, attr) is not None}
    summary = generate(args.out, spec, protocol, args.renderer, options, workers=args.workers,
                       executor=args.executor, address=args.address)
    where = f"Ray cluster at {args.address}" if args.address else f"{summary['workers']} {args.executor} workers"
    print(f"{summary['samples']} samples in {args.out} ({summary['new']} new, {summary['seconds']:.1f} s, {where})")
    return 0


def bench_dataset(spec, workers: int = 2, objects=None, frames: int = 48, executor: str = "local",
                  address: str | None = None) -> dict:
    """Frames per second of base-protocol dataset generation, end to end, plus the parts.

    With ``executor="ray"`` the same protocol also runs on Ray (a local cluster of
    ``workers`` CPUs, or the one at ``address``), reported under ``ray`` with the ratio
    ``ray_over_local`` of end-to-end frames per second.
    """
    from .camera import Camera
    from .executors import make_executor
    from .generate import Job, TapRunner, generate
    from .geometry import membrane_mesh
    from .indenters import INDENTERS

    make_executor(executor, workers, address)  # bad input fails before the first run
    mesh = membrane_mesh(spec)
    protocol = make_protocol("base", spec, mesh, tuple(objects or INDENTERS))
    options = {"field": "plane", "background": "none"}
    with tempfile.TemporaryDirectory() as tmp:
        # The parts, in one process: depth capture and rendering per frame.
        worker = TapRunner(Job(spec, "phong", options, tuple(protocol.objects)))
        taps = protocol.taps[:frames]
        depth_ms, render_ms, depths = [], [], []
        worker.capture(taps[0])
        for tap in taps:
            t0 = time.perf_counter()
            depths.append(worker.capture(tap))
            depth_ms.append((time.perf_counter() - t0) * 1e3)
        for depth in depths:
            t0 = time.perf_counter()
            worker.renderer.render(depth)
            render_ms.append((time.perf_counter() - t0) * 1e3)
        worker.close()
        # End to end: the real command path into a fresh folder.
        summary = generate(Path(tmp) / "ds", spec, protocol, "phong", options, workers=workers, progress=False)
        on_ray = None
        if executor == "ray":
            on_ray = generate(Path(tmp) / "ray", spec, protocol, "phong", options, workers=workers, progress=False,
                              executor="ray", address=address)
    camera = Camera.from_spec(spec)
    results = {
        "frames_per_second": summary["new"] / summary["seconds"],
        "workers": workers,
        "steady_frames_per_second": summary["steady_frames_per_second"],
        "start_up_seconds": summary["start_up_seconds"],
        "ms_per_depth_frame": float(np.median(depth_ms)),
        "ms_per_render": float(np.median(render_ms)),
        "samples": summary["new"],
        "seconds": summary["seconds"],
        "protocol": "base",
        "resolution": [camera.width, camera.height],
        "renderer": "phong, plane field, no background; PNG + depth .npy written per sample",
        "cpus": os.cpu_count(),
        "note": "frames_per_second is end to end (worker start-up, rig compilation, capture, rendering, "
        "file writes); steady_frames_per_second leaves out the start-up, as a long run sees it",
        "executor": "local",
    }
    if on_ray is not None:
        fps = on_ray["new"] / on_ray["seconds"]
        results["ray"] = {
            "frames_per_second": fps,
            "steady_frames_per_second": on_ray["steady_frames_per_second"],
            "start_up_seconds": on_ray["start_up_seconds"],
            "seconds": on_ray["seconds"],
            "cluster": address or f"local, {workers} CPUs",
        }
        results["ray_over_local"] = fps / results["frames_per_second"]
        steady = (on_ray["steady_frames_per_second"], summary["steady_frames_per_second"])
        results["ray_over_local_steady"] = steady[0] / steady[1] if all(steady) else None
    return results


def cmd_bench_dataset(args) -> int:
    from .dataset import atomic_write_json

    results = bench_dataset(load_spec(args.spec), workers=args.workers, executor=args.executor, address=args.address)
    atomic_write_json(Path(args.json), results)
    keys = ("frames_per_second", "workers", "ms_per_depth_frame", "ms_per_render", "ray_over_local")
    print(json.dumps({k: results[k] for k in keys if k in results}))
    return 0


def register(registry) -> None:
    p = registry.command("scene", cmd_scene, "the MuJoCo tapping rig: view it, snapshot it headless, or export its XML")
    p.add_argument("action", choices=["view", "snapshot", "export"])
    p.add_argument("--spec", metavar="TOML")
    p.add_argument("--object", default="sphere",
                   help="indenter name or STL path (default sphere); export takes 'all' or a comma list")
    p.add_argument("--tap", type=int, default=0, help="base-protocol tap to show (default 0)")
    p.add_argument("-o", "--output", default="rig_snapshot.png", help="PNG (snapshot) or folder (export)")
    p.add_argument("--width", type=int, default=1280)
    p.add_argument("--height", type=int, default=960)

    p = registry.command("dataset", cmd_dataset, "run a tapping protocol in MuJoCo and render a dataset (resumable)")
    p.add_argument("--spec", metavar="TOML")
    p.add_argument("--protocol", choices=["base", "extended"], default="base")
    p.add_argument("--objects", default="all", help="'all' or comma-separated indenter names / STL paths")
    p.add_argument("--seed", type=int, default=0, help="seed of the extended protocol's perturbations")
    p.add_argument("--renderer", default="phong", help="phong (the fast path) or pbr (the physically based reference)")
    p.add_argument("--field", help="phong: light field (default plane)")
    p.add_argument("--background", help="phong: none (default), solid, or a no-contact image path")
    p.add_argument("--rectify", action="store_true", default=None, help="phong: rectify the light vectors")
    p.add_argument("--elastic", choices=MODELS,
                   help="phong: the membrane model, published (the paper's smoothing, default) or layer (the "
                        "elastic layer the pbr renderer deforms, so both renderers see one surface)")
    p.add_argument("--target-rse", type=float, metavar="R",
                   help="pbr: add passes until the RMS relative standard error over the contact is at most R "
                        "(default 0.05)")
    p.add_argument("--max-passes", type=int, metavar="N", help="pbr: at most N passes per sample (default 16)")
    p.add_argument("--effect", action="append", metavar="NAME=VALUE",
                   help="pbr: set one physical effect of pbr_tactile.effects.Effects (repeatable)")
    p.add_argument("--estimator", help="pbr: photons (default) or volpath")
    p.add_argument("--photons", type=int, help="pbr: photons per LED per pass")
    p.add_argument("--camera-spp", type=int, help="pbr: camera samples per pixel per pass")
    p.add_argument("--kernel-radius-mm", type=float, help="pbr: radius of the photon density estimate, mm")
    p.add_argument("--no-contact-runs", type=int, metavar="M",
                   help="pbr: no-contact photon runs per pass in the cached no-contact map (0: off)")
    p.add_argument("--film", type=_film_size, metavar="WxH",
                   help="pbr: render at WxH (the camera's aspect) and resample to the camera's size")
    p.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1))
    p.add_argument("--limit", type=int, default=0, help="only the first N taps (0: all)")
    p.add_argument("--executor", default="local",
                   help="local (processes on this machine, default) or ray (a Ray cluster; only this process "
                        "writes files)")
    p.add_argument("--address", metavar="HOST:PORT",
                   help="ray: the head of a running Ray cluster (default: start one here with --workers CPUs)")
    p.add_argument("--out", required=True, metavar="DIR")

    p = registry.bench("dataset", cmd_bench_dataset, "frames per second of base-protocol dataset generation")
    p.add_argument("--spec", metavar="TOML")
    p.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1))
    p.add_argument("--executor", default="local",
                   help="local (default), or ray: run on Ray as well and report ray_over_local")
    p.add_argument("--address", metavar="HOST:PORT", help="ray: a running cluster's head (default: a local one)")
