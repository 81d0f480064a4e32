"""A capture session: run a tapping protocol on the rig and write a capture dataset.

:func:`prepare` plans the whole session and checks it against the safety envelope
before any port is opened; :meth:`Session.run` then drives the devices step by step and
writes each tap's sample (``docs/dataset-format.md``, ``source: "real"``) as soon as it is
captured: its image, then its line, with the commanded and the measured pose. A session
run on a folder that already holds part of it resumes after the last complete sample,
with none lost or duplicated (the writer is ``scenes.dataset.DatasetWriter``): the rig
homes again and carries on with the taps not yet recorded.

On any fault while the rig moves (an exception, a timeout, Ctrl-C, a printer error) the
session stops the machine before it re-raises, as :class:`SessionAborted`:

- a printer that still answers gets ``M410`` (quick stop), and the indenter is backed out
  along the tap's normal and raised to the safe height, when that path is inside the
  envelope from where the printer says the head is;
- a printer that does not answer, reported an error, or cannot be retracted safely gets
  ``M112`` (emergency stop), which needs no answer.

The dataset stays consistent either way: a sample's line is written only after its image.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Callable

import numpy as np

from scenes.dataset import DatasetWriter, atomic_write_json, read_meta, sample_id, write_sample_files
from scenes.errors import TactileSimError
from scenes.kinematics import JOINTS, RigLayout, head_for_tap, sensor_to_world

from . import plan as P
from .envelope import SafetyEnvelope
from .marlin import PrinterError

log = logging.getLogger(__name__)

#: An M400 may take this many times the queued moves' duration at their feed rates
#: (acceleration, slow-downs), plus :data:`WAIT_MARGIN_S`, before the printer counts as
#: silent (its ``busy:`` keep-alive lines restart the wait).
WAIT_FACTOR = 2.0
WAIT_MARGIN_S = 2.0
#: How long the servos get to reach a new angle before the next move, seconds (an HS-422
#: turns 60 degrees in 0.21 s unloaded).
SERVO_SETTLE_S = 0.6


class SessionAborted(TactileSimError, RuntimeError):
    """A session stopped on a fault; the machine was stopped and the dataset is consistent."""


@dataclass
class Devices:
    """What a session drives.

    printer : rig.marlin.MarlinPrinter (home, move_to, wait_for_moves, position,
        quick_stop, emergency_stop).
    servos : rig.servos.ServoBoard (set_angles, angles).
    camera : grab() -> (H, W, 3) float in [0, 1], settle(), describe() -> dict.
    mount : called with an indenter's name when the operator must put it on (the virtual
        rig mounts it itself).
    servo_settle_s : the wait after turning the servos.
    """

    printer: object
    servos: object
    camera: object
    mount: Callable[[str], None] = lambda name: None
    servo_settle_s: float = SERVO_SETTLE_S


@dataclass
class Session:
    """A planned session (see :func:`prepare`)."""

    root: Path
    spec: object
    protocol: object
    layout: RigLayout
    envelope: SafetyEnvelope
    vertices: dict[str, np.ndarray]
    meta: dict
    done: set[str]
    steps: list[P.Step]
    after_background: Callable[[np.ndarray], dict] | None = None
    hidden: dict | None = None

    @cached_property
    def _taps(self) -> dict:
        """Tap index -> tap."""
        return {t.index: t for t in self.protocol.taps}

    @property
    def todo(self) -> list:
        return [t for t in self.protocol.taps if sample_id(t.index, t.object) not in self.done]

    def stream(self) -> list[tuple[str, str]]:
        """Every line the session would send, as ``(device, line)`` (the ``--dry-run``)."""
        return [line for step in self.steps for line in P.device_lines(step, self.layout)]

    # ------------------------------------------------------------------ running

    def run(self, devices: Devices, progress: bool = True) -> dict:
        """Drive the devices through the plan; returns a summary.

        Raises SessionAborted (from the fault) after stopping the machine.
        """
        from tqdm import tqdm

        described = devices.camera.describe()
        meta = {**self.meta, "renderer": {"renderer": "camera", "camera": described}}
        if described.get("size"):
            meta["image_size"] = list(described["size"])
        writer = DatasetWriter(self.root, meta, self.protocol.to_dict())
        if self.hidden is not None:
            atomic_write_json(self.root / "virtual.json", self.hidden)
        # The writer may know samples that prepare() did not see (another run since).
        skip = {i for i, t in self._taps.items() if sample_id(i, t.object) in writer.done}
        steps = [s for s in self.steps if s.tap is None or s.tap not in skip]
        bar = tqdm(total=len(self.protocol.taps), initial=len(writer.done), desc="rig", unit="tap",
                   disable=not progress)
        t0, new = time.perf_counter(), 0
        state = {"step": None}
        self._queued_s, self._head = 0.0, None
        try:
            for step in steps:
                state["step"] = step
                if self._do(step, devices, writer):
                    new += 1
                    bar.update(1)
        except BaseException as exc:
            bar.close()
            stopped = self._stop(devices, state["step"], exc)
            where = P.describe(state["step"]) if state["step"] is not None else "the start"
            cause = "interrupted (Ctrl-C)" if isinstance(exc, KeyboardInterrupt) else f"{type(exc).__name__}: {exc}"
            raise SessionAborted(
                f"capture session in {self.root} stopped at {where}: {cause}. {stopped} "
                f"{len(writer.done)} of {len(self.protocol.taps)} samples are recorded; run the same command "
                "again to resume") from exc
        bar.close()
        return {"samples": len(writer.done), "new": new, "seconds": time.perf_counter() - t0}

    def _do(self, step: P.Step, devices: Devices, writer: DatasetWriter) -> bool:
        printer, layout = devices.printer, self.layout
        if step.kind == P.HOME:
            printer.home()
            self._head = layout.head_position(np.zeros(3))
        elif step.kind == P.MOVE:
            printer.move_to(layout.printer_position(step.head), step.feed)
            if self._head is not None:
                self._queued_s += float(np.linalg.norm(np.asarray(step.head) - self._head)) / step.feed
            self._head = np.asarray(step.head)
        elif step.kind == P.WAIT:
            printer.wait_for_moves(WAIT_FACTOR * self._queued_s + WAIT_MARGIN_S)
            self._queued_s = 0.0
        elif step.kind == P.SERVOS:
            devices.servos.set_angles(step.roll, step.pitch)
            if devices.servo_settle_s > 0:
                time.sleep(devices.servo_settle_s)
        elif step.kind == P.MOUNT:
            devices.mount(step.obj)
        elif step.kind == P.CAPTURE:
            devices.camera.settle()
            image = np.asarray(devices.camera.grab(), dtype=np.float32)
            if step.tap is None:
                self._background(image, writer)
                return False
            self._sample(self._taps[step.tap], image, devices, writer)
            return True
        return False

    def _background(self, image: np.ndarray, writer: DatasetWriter) -> None:
        writer.write_background(image)
        if self.after_background is not None:
            extra = self.after_background(image)
            if extra:
                meta = read_meta(self.root)
                atomic_write_json(self.root / "dataset.json", {**meta, **extra})

    def _sample(self, tap, image: np.ndarray, devices: Devices, writer: DatasetWriter) -> None:
        from scenes.generate import tap_fields

        head = self.layout.head_position(devices.printer.position())
        roll, pitch = devices.servos.angles()
        press = head_for_tap(tap, self.vertices[tap.object], self.layout)
        commanded = self._pose(press, tap.sensor_roll, tap.indenter_pitch)
        measured = self._pose(head, roll, pitch)
        n_world = sensor_to_world(tap.sensor_roll) @ np.asarray(tap.normal)
        # Deeper by how much farther along -normal the head went than it was told.
        depth = tap.depth + float((press - head) @ n_world)
        record = {**tap_fields(tap), "commanded_pose": commanded, "measured_pose": measured, "measured_depth": depth}
        files = write_sample_files(writer.root, record["id"], image, None)
        writer.append({**record, **files})

    @staticmethod
    def _pose(head, roll: float, pitch: float) -> dict[str, float]:
        values = (*np.asarray(head, dtype=np.float64).tolist(), float(pitch), float(roll))
        return dict(zip(JOINTS, values))

    # ------------------------------------------------------------------ faults

    def _stop(self, devices: Devices, step: P.Step | None, exc: BaseException) -> str:
        """Stop the machine after a fault; returns what was done, for the message."""
        printer = devices.printer
        if isinstance(exc, PrinterError):
            return _emergency(printer, f"the printer failed ({type(exc).__name__}), so it got M112")
        try:
            printer.quick_stop()
        except BaseException as stop_exc:  # noqa: BLE001 - any failure here means M112
            return _emergency(printer, f"M410 failed ({stop_exc}), so the printer got M112")
        if step is None or step.tap is None:
            return "The printer got M410 (quick stop)."
        tap = self._taps[step.tap]
        try:
            head = self.layout.head_position(printer.position())
            _, approach, above = P.waypoints(tap, self.vertices[tap.object], self.layout)
            # The servos may have been turning: retract only as the envelope allows from
            # where they were told to be for this tap.
            self.envelope.check_move(tap.object, head, approach, tap.indenter_pitch, tap.sensor_roll,
                                     "retracting after a fault", press=True)
            self.envelope.check_move(tap.object, approach, above, tap.indenter_pitch, tap.sensor_roll,
                                     "retracting after a fault")
            printer.move_to(self.layout.printer_position(approach), P.PRESS_FEED_M_S)
            printer.move_to(self.layout.printer_position(above), P.TRAVEL_FEED_M_S)
            printer.wait_for_moves()
        except BaseException as retract_exc:  # noqa: BLE001
            return _emergency(printer, f"the printer got M410, but retracting failed ({retract_exc}), so it got M112")
        return "The printer got M410 (quick stop) and the indenter was retracted to the safe height."


def _emergency(printer, what: str) -> str:
    try:
        printer.emergency_stop()
    except BaseException as exc:  # noqa: BLE001 - nothing more can be done
        log.error("M112 could not be sent: %s", exc)
        return f"{what.rstrip('.')}; M112 could not be sent either ({exc}): switch the printer off."
    return what[0].upper() + what[1:] + "."


def prepare(root, spec, protocol, layout: RigLayout = RigLayout(), *, source_meta: dict | None = None,
            after_background: Callable[[np.ndarray], dict] | None = None, hidden: dict | None = None) -> Session:
    """Plan a session and check it, before any device is touched.

    Checks the protocol against the sensor (``scenes.protocol_checks.validate``) and every move
    against the safety envelope (EnvelopeError naming the tap and move, nothing sent), and
    reads what an existing folder already holds (a resumed session plans only the rest).

    Parameters
    ----------
    root : the capture dataset's folder (created on run).
    source_meta : extra dataset.json keys (e.g. ``{"rig": {...}}``).
    after_background : called with the background image once it is captured; returns
        keys to add to dataset.json (e.g. the alignment).
    hidden : the virtual rig's settings, written to ``virtual.json`` (never read by the
        diagnosis).
    """
    from scenes.camera import Camera
    from scenes.dataset import read_samples
    from scenes.geometry import membrane_mesh
    from scenes.indenters import indenter
    from scenes.protocol_checks import validate

    root = Path(root)
    mesh = membrane_mesh(spec)
    vertices = {name: np.asarray(indenter(name).vertices, dtype=np.float64) for name in protocol.objects}
    validate(protocol, spec, mesh)
    envelope = SafetyEnvelope.for_sensor(spec, mesh, vertices, layout)
    done = set()
    if (root / "samples.jsonl").exists():
        done = {r["id"] for r in read_samples(root)}
    camera = Camera.from_spec(spec)
    meta = {
        "source": "real",
        "sensor": spec.to_dict(),
        "protocol": {"name": protocol.name, "seed": protocol.seed, "taps": len(protocol.taps),
                     "objects": list(protocol.objects)},
        "image_size": [camera.width, camera.height],
        "image": "8-bit RGB PNG from the camera",
        "depth": "none: a real capture has no depth map",
    }
    extra = dict(source_meta or {})
    meta["rig"] = {"layout": layout.to_dict(), "virtual": False, **extra.pop("rig", {})}
    meta.update(extra)
    todo = [t for t in protocol.taps if sample_id(t.index, t.object) not in done]
    steps = P.plan(todo, vertices, layout, envelope, background=not (root / "background.png").exists())
    return Session(root, spec, protocol, layout, envelope, vertices, meta, done, steps, after_background, hidden)
