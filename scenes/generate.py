"""Dataset generation: run a tapping protocol on the MuJoCo rig, capture depth, render.

Renderers are plugins (entry point group ``tactile_sim.renderers``: a module with
``prepare(spec, mesh, camera, options) -> settings`` and
``make_renderer(spec, mesh, camera, ref_depth, options)``), so this module never imports
one. Work runs in local processes; the parent alone appends to ``samples.jsonl``.
"""

from __future__ import annotations

import dataclasses
import multiprocessing
import os
import time
from dataclasses import dataclass
from importlib.metadata import entry_points
from pathlib import Path

import numpy as np

from .camera import Camera
from .dataset import DatasetWriter, sample_id, write_sample_files
from .geometry import membrane_mesh
from .protocol import Protocol, Tap, validate
from .spec import SensorSpec

RENDERER_GROUP = "tactile_sim.renderers"


def renderer_plugin(name: str):
    found = {ep.name: ep for ep in entry_points(group=RENDERER_GROUP)}
    if name not in found:
        raise ValueError(f"renderer must be one of {sorted(found)}, got {name!r}")
    return found[name].load()


def measured_depth(depth: np.ndarray, ref_depth: np.ndarray, camera: Camera, tap: Tap, noise: float) -> float:
    """Deepest indentation in a captured depth map, along the tap's normal, metres.

    max over contact pixels of (p - P) . n, with p the tap's contact point and P the
    back-projected pixels where the depth is nearer than D_ref; 0 without contact.
    """
    hit = depth < ref_depth - noise
    if not hit.any():
        return 0.0
    P = depth[hit, None].astype(np.float64) * camera.rays[hit]
    return float(((np.asarray(tap.point) - P) @ np.asarray(tap.normal)).max())


@dataclass(frozen=True)
class Job:
    """Everything a worker needs, picklable."""

    root: str
    spec: SensorSpec
    renderer: str
    options: dict
    noise_m: float = 1e-6


class Worker:
    """Per-process state: one compiled rig carrying every object, the renderer, D_ref."""

    def __init__(self, job: Job, objects: tuple[str, ...]):
        from .indenters import indenter
        from .rig import Rig, rig_scene

        self.job = job
        self.spec = job.spec
        self.mesh = membrane_mesh(job.spec)
        self.camera = Camera.from_spec(job.spec)
        meshes = {name: indenter(name) for name in objects}
        self.rig = Rig(rig_scene(self.spec, meshes, membrane=self.mesh), self.spec)
        self.rig.home()
        self.ref_depth = self.rig.depth()
        plugin = renderer_plugin(job.renderer)
        self.renderer = plugin.make_renderer(self.spec, self.mesh, self.camera, self.ref_depth, job.options)

    def capture(self, tap: Tap) -> np.ndarray:
        self.rig.press(tap)
        return self.rig.depth()

    def run(self, tap: Tap) -> dict:
        depth = self.capture(tap)
        image = self.renderer.render(depth)
        sid = sample_id(tap.index, tap.object)
        files = write_sample_files(self.job.root, sid, image, depth)
        return {
            "id": sid,
            "object": tap.object,
            "path": tap.row,
            "position": tap.position,
            "replica": tap.replica,
            "tap_index": tap.index,
            "sensor_roll": tap.sensor_roll,
            "indenter_pitch": tap.indenter_pitch,
            "spin": tap.spin,
            "contact_point": list(tap.point),
            "normal": list(tap.normal),
            "commanded_depth": tap.depth,
            "measured_depth": measured_depth(depth, self.ref_depth, self.camera, tap, self.job.noise_m),
            **files,
        }


_WORKER: Worker | None = None


def _init_worker(job: Job, objects: tuple[str, ...], gl_threads: str | None = None) -> None:
    global _WORKER
    if gl_threads is not None:
        # Mesa's software rasteriser starts a thread per core in every process; with one
        # process per core they only contend.
        os.environ.setdefault("LP_NUM_THREADS", gl_threads)
    _WORKER = Worker(job, objects)


def _run(tap: Tap) -> dict:
    return _WORKER.run(tap)


def _no_contact(_=None) -> np.ndarray:
    return _WORKER.renderer.no_contact


def generate(
    root: str | Path,
    spec: SensorSpec,
    protocol: Protocol,
    renderer: str = "phong",
    options: dict | None = None,
    workers: int = 2,
    source: str = "sim",
    progress: bool = True,
) -> dict:
    """Run (or resume) a protocol into a dataset folder; returns a summary.

    Taps already recorded in ``samples.jsonl`` are skipped, so a killed run continues
    where it stopped.
    """
    options = dict(options or {})
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    mesh = membrane_mesh(spec)
    camera = Camera.from_spec(spec)
    from .indenters import indenter

    for name in protocol.objects:
        indenter(name)  # unknown names fail here, before any work
    validate(protocol, spec, mesh)
    plugin = renderer_plugin(renderer)
    settings = plugin.prepare(spec, mesh, camera, options)
    meta = {
        "source": source,
        "sensor": dataclasses.asdict(spec),
        "protocol": {"name": protocol.name, "seed": protocol.seed, "taps": len(protocol.taps),
                     "objects": list(protocol.objects)},
        "renderer": settings,
        "image_size": [camera.width, camera.height],
        "depth": "planar z, metres, float32 (H, W)",
        "image": "8-bit RGB PNG of linear [0, 1] values",
    }
    writer = DatasetWriter(root, meta, protocol.to_dict())
    todo = [t for t in protocol.taps if sample_id(t.index, t.object) not in writer.done]
    job = Job(str(Path(root).resolve()), spec, renderer, options)
    objects = tuple(protocol.objects)
    t0 = time.perf_counter()
    from tqdm import tqdm

    bar = tqdm(total=len(protocol.taps), initial=len(protocol.taps) - len(todo), desc="dataset", unit="sample",
               disable=not progress)
    need_background = not (writer.root / "background.png").exists() and bool(objects)
    if workers == 1 or len(todo) <= 1:
        if need_background or todo:
            _init_worker(job, objects)
        if need_background:
            writer.write_background(_no_contact())
        stamps = _finish(writer, map(_run, todo), bar)
    else:
        ctx = multiprocessing.get_context("spawn")  # EGL contexts must not cross a fork
        with ctx.Pool(workers, initializer=_init_worker, initargs=(job, objects, "1")) as pool:
            background = pool.apply_async(_no_contact) if need_background else None
            stamps = _finish(writer, pool.imap_unordered(_run, todo, chunksize=4), bar)
            if background is not None:
                writer.write_background(background.get())
    bar.close()
    seconds = time.perf_counter() - t0
    steady = (len(stamps) - 1) / (stamps[-1] - stamps[0]) if len(stamps) > 2 and stamps[-1] > stamps[0] else None
    return {
        "samples": len(writer.done),
        "new": len(todo),
        "seconds": seconds,
        "workers": workers,
        "start_up_seconds": (stamps[0] - t0) if stamps else None,
        "steady_frames_per_second": steady,
    }


def _finish(writer: DatasetWriter, results, bar) -> list[float]:
    """Record results as they come; returns when each was recorded (perf_counter)."""
    stamps = []
    for record in results:
        writer.append(record)
        stamps.append(time.perf_counter())
        bar.update(1)
    return stamps
