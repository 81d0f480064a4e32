"""Subcommands of the scenes package: the MuJoCo rig (scene), datasets, and their bench."""

from __future__ import annotations

import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np

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


def cmd_dataset(args) -> int:
    from .generate import generate
    from .geometry import membrane_mesh

    spec = load_spec(args.spec)
    protocol = make_protocol(args.protocol, spec, membrane_mesh(spec), _objects(args.objects), seed=args.seed)
    if args.limit:
        from dataclasses import replace

        protocol = replace(protocol, taps=protocol.taps[: args.limit])
    options = {"field": args.field, "background": args.background, "rectify": args.rectify}
    summary = generate(args.out, spec, protocol, args.renderer, options, workers=args.workers)
    print(
        f"{summary['samples']} samples in {args.out} ({summary['new']} new, {summary['seconds']:.1f} s, "
        f"{summary['workers']} workers)"
    )
    return 0


def bench_dataset(spec, workers: int = 2, objects=None, frames: int = 48) -> dict:
    """Frames per second of base-protocol dataset generation, end to end, plus the parts."""
    from .camera import Camera
    from .generate import Job, Worker, generate
    from .geometry import membrane_mesh
    from .indenters import INDENTERS

    mesh = membrane_mesh(spec)
    protocol = make_protocol("base", spec, mesh, tuple(objects or INDENTERS))
    options = {"field": "plane", "background": "none"}
    with tempfile.TemporaryDirectory() as tmp:
        # The parts, in one process: depth capture and rendering per frame.
        worker = Worker(Job(tmp, spec, "phong", options), protocol.objects)
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
        worker.rig.close()
        # End to end: the real command path into a fresh folder.
        summary = generate(Path(tmp) / "ds", spec, protocol, "phong", options, workers=workers, progress=False)
    camera = Camera.from_spec(spec)
    return {
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
    }


def cmd_bench_dataset(args) -> int:
    from .dataset import atomic_write_json

    results = bench_dataset(load_spec(args.spec), workers=args.workers)
    atomic_write_json(Path(args.json), results)
    print(json.dumps({k: results[k] for k in ("frames_per_second", "workers", "ms_per_depth_frame", "ms_per_render")}))
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
    p.add_argument("--renderer", default="phong")
    p.add_argument("--field", default="plane", help="light field of the phong renderer")
    p.add_argument("--background", default="none", help="none, solid, or a no-contact image path")
    p.add_argument("--rectify", action="store_true")
    p.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1))
    p.add_argument("--limit", type=int, default=0, help="only the first N taps (0: all)")
    p.add_argument("--out", required=True, metavar="DIR")

    p = registry.bench("dataset", cmd_bench_dataset, "frames per second of base-protocol dataset generation")
    p.add_argument("--spec", metavar="TOML")
    p.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1))
