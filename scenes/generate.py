"""Dataset generation: run a tapping protocol on the MuJoCo rig, capture depth, render.

Renderers are plugins (entry point group ``tactile_sim.renderers``: a module with
``prepare(spec, mesh, camera, options) -> settings`` and
``make_renderer(spec, mesh, camera, ref_depth, options)``), so this module never imports
one. Work runs in local processes; the parent alone appends to ``samples.jsonl``.
"""

from __future__ import annotations

import dataclasses
import multiprocessing
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
    """Per-process state: one compiled rig per object, the renderer, D_ref."""

    def __init__(self, job: Job):
        from .rig import Rig, rig_scene

        self.job = job
        self.spec = job.spec
        self.mesh = membrane_mesh(job.spec)
        self.camera = Camera.from_spec(job.spec)
        self._rig_scene, self._rig_class = rig_scene, Rig
        self.rigs: dict = {}
        self.renderer = None

    def rig(self, name: str):
        if name not in self.rigs:
            from .indenters import indenter

            scene = self._rig_scene(self.spec, indenter(name), name, membrane=self.mesh)
            self.rigs[name] = self._rig_class(scene, self.spec)
            if self.renderer is None:
                rig = self.rigs[name]
                rig.home()
                self.ref_depth = rig.depth()
                plugin = renderer_plugin(self.job.renderer)
                self.renderer = plugin.make_renderer(self.spec, self.mesh, self.camera, self.ref_depth, self.job.options)
        return self.rigs[name]

    def capture(self, tap: Tap) -> np.ndarray:
        rig = self.rig(tap.object)
        rig.press(tap)
        return rig.depth()

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


def _init_worker(job: Job) -> None:
    global _WORKER
    _WORKER = Worker(job)


def _run(tap: Tap) -> dict:
    return _WORKER.run(tap)


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
    t0 = time.perf_counter()
    if not (writer.root / "background.png").exists() and protocol.taps:
        local = Worker(job)
        local.rig(protocol.taps[0].object)
        writer.write_background(local.renderer.no_contact)
        for rig in local.rigs.values():
            rig.close()
    from tqdm import tqdm

    bar = tqdm(total=len(protocol.taps), initial=len(protocol.taps) - len(todo), desc="dataset", unit="sample",
               disable=not progress)
    if workers == 1 or len(todo) <= 1:
        _init_worker(job)
        results = map(_run, todo)
        _finish(writer, results, bar)
    else:
        ctx = multiprocessing.get_context("spawn")  # EGL contexts must not cross a fork
        with ctx.Pool(workers, initializer=_init_worker, initargs=(job,)) as pool:
            _finish(writer, pool.imap_unordered(_run, todo, chunksize=4), bar)
    bar.close()
    seconds = time.perf_counter() - t0
    return {"samples": len(writer.done), "new": len(todo), "seconds": seconds, "workers": workers}


def _finish(writer: DatasetWriter, results, bar) -> None:
    for record in results:
        writer.append(record)
        bar.update(1)
