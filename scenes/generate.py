"""Dataset generation: run a tapping protocol on the MuJoCo rig, capture depth, render.

A tap is one task, ``run_tap(job, task, shared)``: it presses the indenter (or, for a
``PosedTap``, sets the rig's joints to an explicit pose, e.g. a capture's measured one),
captures the depth map, renders it and encodes the sample's files; it writes nothing.
The same task runs in local processes or on a Ray cluster (``scenes.executors``), and
the driver alone (``run_tasks``) writes the files and appends the line to ``samples.jsonl``.

Renderers are plugins (``scenes.renderers.RendererPlugin``) that the caller passes in
(the command line looks one up by name), so this module never imports one, nor chooses
one: a job carries the plugin's ``make_renderer``, which each worker runs once.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .camera import Camera
from .dataset import DatasetWriter, sample_files, sample_id, write_files
from .executors import Tasks, make_executor
from .geometry import membrane_mesh
from .protocol_checks import validate
from .renderers import (
    DatasetRenderer,
    OwnDepth,
    RendererPlugin,
    SampleRenderer,
    SharesInputs,
    build_renderer,
    check_plugin,
)
from .spec import SensorSpec
from .taps import Protocol, Tap


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
    """What a tap task needs besides the tap, picklable. It never holds the dataset
    folder: tasks run wherever the executor puts them, with no disk shared.

    make_renderer : the renderer plugin's ``make_renderer``, a module-level function, so
        that a job pickles (by reference) to any worker.
    """

    spec: SensorSpec
    make_renderer: Callable[..., DatasetRenderer]
    options: dict
    objects: tuple[str, ...]
    noise_m: float = 1e-6

    def __post_init__(self):
        if not callable(self.make_renderer):
            raise ValueError(f"make_renderer must be a renderer plugin's make_renderer function, got "
                             f"{self.make_renderer!r}")


@dataclass(frozen=True)
class PosedTap:
    """A tap task at an explicit joint pose: the rig is set to ``pose`` instead of being
    pressed by ``Rig.tap_pose``; ``tap`` still gives the sample's id and fields.

    pose : joint name -> value (``scenes.kinematics.JOINTS``: the head's position in metres,
        world frame, and the servos' angles in radians), e.g. a capture's measured pose.
    """

    tap: Tap
    pose: dict


#: What a tap task runs: a protocol's tap, or a tap at an explicit pose.
Task = Tap | PosedTap


def task_tap(task: Task) -> Tap:
    """The protocol tap of a task."""
    return task.tap if isinstance(task, PosedTap) else task


def tap_fields(tap: Tap) -> dict:
    """The protocol's fields of a tap's sample record (docs/dataset-format.md)."""
    return {
        "id": sample_id(tap.index, tap.object),
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
    }


def render_sample(renderer, depth: np.ndarray) -> dict:
    """``{"image", "arrays", "record"}`` of one depth map, from ``render_sample`` when the
    renderer has it (``scenes.renderers.SampleRenderer``), else from ``render`` alone."""
    if isinstance(renderer, SampleRenderer):
        out = renderer.render_sample(depth)
        return {"image": out["image"], "arrays": dict(out.get("arrays") or {}), "record": dict(out.get("record") or {})}
    return {"image": renderer.render(depth), "arrays": {}, "record": {}}


class TapRunner:
    """Per-process state of tap tasks: one compiled rig carrying every object, D_ref and
    the renderer. Expensive to build, so each process keeps one (``runner``)."""

    def __init__(self, job: Job, shared=None):
        from .indenters import indenter
        from .rig import Rig, rig_scene

        self.job = job
        self.spec = job.spec
        self.mesh = membrane_mesh(job.spec)
        self.camera = Camera.from_spec(job.spec)
        meshes = {name: indenter(name) for name in job.objects}
        self.rig = Rig(rig_scene(self.spec, meshes, membrane=self.mesh), self.spec)
        self.rig.home()
        self.ref_depth = self.rig.depth()
        self.renderer = build_renderer(job.make_renderer, self.spec, self.mesh, self.camera, self.ref_depth,
                                       job.options, shared)

    def capture(self, task: Task) -> np.ndarray:
        """The depth map of a tap pressed, or of the rig set to a posed tap's joints."""
        if not isinstance(task, PosedTap):
            self.rig.press(task)
            return self.rig.depth()
        self.rig.mount(task.tap.object)
        try:
            self.rig.set_joints(**task.pose)
        except ValueError as exc:
            raise ValueError(f"sample {sample_id(task.tap.index, task.tap.object)}: pose: {exc}") from None
        return self.rig.depth()

    def run(self, task: Task) -> dict:
        """One task -> ``{"record", "image" (H, W, 3) float32, "depth" (H, W) float32
        metres (None where the renderer's ``writes_depth`` is False), "arrays" {name:
        float32 array}}``. A posed tap's record holds its
        ``pose``."""
        tap = task_tap(task)
        depth = np.asarray(self.capture(task), np.float32)
        out = render_sample(self.renderer, depth)
        record = {**tap_fields(tap),
                  "measured_depth": measured_depth(depth, self.ref_depth, self.camera, tap, self.job.noise_m)}
        if isinstance(task, PosedTap):
            record["pose"] = {name: float(value) for name, value in task.pose.items()}
        clash = sorted((set(out["record"]) | set(out["arrays"])) & (set(record) | {"image", "depth"}))
        if clash:
            raise ValueError(f"renderer {self.job.make_renderer.__module__!r} returned fields {clash} that a sample "
                             f"record already has; rename them")
        return {
            "record": {**record, **out["record"]},
            "image": np.asarray(out["image"], np.float32),
            "depth": None if isinstance(self.renderer, OwnDepth) and not self.renderer.writes_depth else depth,
            "arrays": {name: np.asarray(a, np.float32) for name, a in out["arrays"].items()},
        }

    def close(self) -> None:
        self.rig.close()


_RUNNER: TapRunner | None = None


def runner(job: Job, shared=None) -> TapRunner:
    """This process's TapRunner for ``job``, built on first use and kept.

    ``shared`` is the plugin's ``shared()`` of the same job, so the job alone keys it.
    """
    global _RUNNER
    if _RUNNER is None or _RUNNER.job != job:
        if _RUNNER is not None:
            _RUNNER.close()
            _RUNNER = None
        _RUNNER = TapRunner(job, shared)
    return _RUNNER


def run_tap(job: Job, task: Task, shared=None) -> dict:
    """The task of one tap: press (or pose), capture depth, render, and encode the
    sample's files (PNG, .npy) where it ran, so that the driver, which writes every file,
    only writes bytes; writes nothing.

    Returns ``{"record": {...JSON fields...}, "files": {key: (relative path, bytes)}}``
    (``scenes.dataset.sample_files``: its image, depth and the renderer's arrays).
    """
    result = runner(job, shared).run(task)
    sid = result["record"]["id"]
    return {"record": result["record"],
            "files": sample_files(sid, result["image"], result["depth"], result["arrays"])}


def no_contact(job: Job, shared=None) -> np.ndarray:
    """The renderer's no-contact image, (H, W, 3) float in [0, 1]."""
    return np.asarray(runner(job, shared).renderer.no_contact, np.float32)


#: What the executors run: a tap's task and the no-contact image's.
TASKS = Tasks(tap=run_tap, no_contact=no_contact)


def record_sample(writer: DatasetWriter, result: dict) -> None:
    """Write one task's result into the dataset: its files, then its line (driver only)."""
    writer.append({**result["record"], **write_files(writer.root, result["files"])})


def generate(
    root: str | Path,
    spec: SensorSpec,
    protocol: Protocol,
    renderer: RendererPlugin,
    options: dict | None = None,
    workers: int = 2,
    source: str | None = None,
    progress: bool = True,
    executor: str = "local",
    address: str | None = None,
) -> dict:
    """Run (or resume) a protocol into a dataset folder; returns a summary.

    Taps already recorded in ``samples.jsonl`` are skipped, so a killed run continues
    where it stopped.

    Parameters
    ----------
    renderer : the renderer plugin (``scenes.renderers.RendererPlugin``, e.g. the module
        ``phong_reference.plugin``), and ``options`` its options.
    workers : local processes (``executor="local"``), or the CPUs of the Ray cluster
        started on this machine (``executor="ray"`` without ``address``).
    executor : ``"local"`` (a process pool on this machine) or ``"ray"``.
    address : a Ray cluster's ``HOST:PORT`` to connect to (``executor="ray"`` only).
    source : the dataset's ``source`` (scenes.dataset.SOURCES); None: the plugin's
        ``SOURCE`` ("pbr" for the physically based reference, "sim" for the fast path).
    """
    options = dict(options or {})
    mesh = membrane_mesh(spec)
    from .indenters import indenter

    for name in protocol.objects:
        indenter(name)  # unknown names fail here, before any work
    validate(protocol, spec, mesh)
    meta = {"source": source,
            "protocol": {"name": protocol.name, "seed": protocol.seed, "taps": len(protocol.taps),
                         "objects": list(protocol.objects)}}
    return run_tasks(root, spec, list(protocol.taps), tuple(protocol.objects), protocol.to_dict(), meta, renderer,
                     options, workers=workers, progress=progress, executor=executor, address=address)


def run_tasks(
    root: str | Path,
    spec: SensorSpec,
    tasks: list[Task],
    objects: tuple[str, ...],
    protocol: dict,
    meta: dict,
    renderer: RendererPlugin,
    options: dict | None = None,
    workers: int = 2,
    progress: bool = True,
    executor: str = "local",
    address: str | None = None,
) -> dict:
    """Run (or resume) tap tasks into a dataset folder; returns a summary (``generate``).

    tasks : taps or posed taps; those whose sample id is already in ``samples.jsonl``
        are skipped.
    objects : every indenter the rig must carry.
    protocol : the full protocol dict, written as ``protocol.json``.
    meta : dataset.json keys besides those this fills in (sensor, renderer, image_size,
        depth, image); ``source`` None means the plugin's ``SOURCE``.
    """
    options = dict(options or {})
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    runs = make_executor(executor, workers, address)
    mesh = membrane_mesh(spec)
    camera = Camera.from_spec(spec)
    plugin = check_plugin(renderer)
    settings = plugin.prepare(spec, mesh, camera, options)
    meta = {
        **meta,
        "source": meta.get("source") if meta.get("source") is not None else plugin.SOURCE,
        "sensor": spec.to_dict(),
        "renderer": settings,
        "image_size": [camera.width, camera.height],
        "depth": "planar z, metres, float32 (H, W)",
        "image": "8-bit RGB PNG of linear [0, 1] values",
    }
    writer = DatasetWriter(root, meta, protocol)
    todo = [t for t in tasks if sample_id(task_tap(t).index, task_tap(t).object) not in writer.done]
    job = Job(spec, plugin.make_renderer, options, tuple(objects))
    t0 = time.perf_counter()
    from tqdm import tqdm

    bar = tqdm(total=len(tasks), initial=len(tasks) - len(todo), desc="dataset", unit="sample",
               disable=not progress)
    need_background = not (writer.root / "background.png").exists() and bool(job.objects)
    stamps = []
    if todo or need_background:
        shared = plugin.shared(spec, mesh, camera, options) if isinstance(plugin, SharesInputs) else None
        for kind, value in runs.run(TASKS, job, todo, shared, need_background):
            if kind == "background":
                writer.write_background(value)
                continue
            record_sample(writer, value)
            stamps.append(time.perf_counter())
            bar.update(1)
    bar.close()
    seconds = time.perf_counter() - t0
    steady = (len(stamps) - 1) / (stamps[-1] - stamps[0]) if len(stamps) > 2 and stamps[-1] > stamps[0] else None
    return {
        "samples": len(writer.done),
        "new": len(todo),
        "seconds": seconds,
        "workers": workers,
        "executor": executor,
        "start_up_seconds": (stamps[0] - t0) if stamps else None,
        "steady_frames_per_second": steady,
    }
