"""Replay a capture: each of its taps simulated at the pose the rig measured.

A capture (``docs/dataset-format.md``, ``source: "real"``) holds, per sample, the tap of
its ``protocol.json`` and the rig's ``measured_pose``: the joints the real printer and
servos reached. ``replay`` sets the MuJoCo rig (``scenes.rig.Rig``) to that pose, captures
the depth map and renders it with a renderer plugin (``scenes.generate``: the same tasks,
executors and resumable writer as ``tactile-sim dataset``). The result is a dataset of the
same protocol and sample ids, so ``tactile-sim diagnose CAPTURE SIM`` pairs it sample by
sample.

A replay reads only dataset.json, protocol.json and samples.jsonl of the capture: a
virtual rig's hidden settings (e.g. ``virtual.json``) stay unread.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from .dataset import DatasetError, read_meta, read_samples, sample_id, sha256_json
from .generate import PosedTap, run_tasks
from .taps import Protocol
from .kinematics import JOINTS
from .renderers import RendererPlugin, check_plugin
from .spec import SensorSpec
from .spec_read import spec_from_dict

#: The pose key of a capture's sample record that a replay sets the rig to.
POSE_KEY = "measured_pose"


@dataclass(frozen=True)
class Capture:
    """A capture dataset, checked for replay.

    meta : its dataset.json; protocol : its protocol.json as read (the dataset's sha256
    is of this dict); spec : its sensor; records : its sample records, in file order;
    tasks : one ``PosedTap`` per record, the rig at the sample's measured pose.
    """

    root: Path
    meta: dict
    protocol: dict
    spec: SensorSpec
    records: tuple[dict, ...]
    tasks: tuple[PosedTap, ...]

    @property
    def ids(self) -> list[str]:
        return [r["id"] for r in self.records]

    @property
    def objects(self) -> tuple[str, ...]:
        return tuple(Protocol.from_dict(self.protocol).objects)


def _pose(record: dict, where: str) -> dict[str, float]:
    pose = record.get(POSE_KEY)
    if not isinstance(pose, dict):
        raise DatasetError(f"{where} has no {POSE_KEY} (expected an object of the rig's joints {list(JOINTS)}), "
                           f"got {pose!r}")
    missing = [j for j in JOINTS if j not in pose]
    unknown = sorted(set(pose) - set(JOINTS))
    if missing or unknown:
        wrong = "; ".join(([f"lacks {', '.join(missing)}"] if missing else []) +
                          ([f"has unknown {', '.join(unknown)}"] if unknown else []))
        raise DatasetError(f"{where}: {POSE_KEY} {wrong}; expected exactly the rig's joints {list(JOINTS)}")
    out = {}
    for joint in JOINTS:
        value = pose[joint]
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise DatasetError(f"{where}: {POSE_KEY}.{joint} must be a finite number (metres or radians), got "
                               f"{value!r}")
        out[joint] = float(value)
    return out


def read_capture(root: str | Path) -> Capture:
    """A capture folder, checked for replay; ``DatasetError`` naming the folder, the sample
    and the key when something a replay needs is missing or disagrees."""
    root = Path(root)
    try:
        meta = read_meta(root)
    except DatasetError as exc:
        raise DatasetError(f"capture {exc}") from None
    if meta.get("source") != "real":
        raise DatasetError(f"capture {root}: source is {meta.get('source')!r}; a replay takes a capture of the rig "
                           "(source 'real')")
    path = root / "protocol.json"
    if not path.is_file():
        raise DatasetError(f"capture {root}: protocol.json is missing; a replay takes each sample's tap from it")
    try:
        protocol_dict = json.loads(path.read_text())
        protocol = Protocol.from_dict(protocol_dict)
    except (json.JSONDecodeError, UnicodeDecodeError, ValueError) as exc:
        raise DatasetError(f"capture {path}: {exc}") from None
    expected = (meta.get("protocol") or {}).get("sha256")
    if expected is not None and expected != sha256_json(protocol_dict):
        raise DatasetError(f"capture {root}: protocol.json does not match dataset.json's protocol sha256; the "
                           "capture was edited or mixed with another")
    try:
        spec = spec_from_dict(meta["sensor"], source=f"{root}/dataset.json sensor")
    except (KeyError, TypeError) as exc:
        raise DatasetError(f"capture {root}/dataset.json has no usable sensor spec: {exc!r}") from None
    size = [spec.camera.width, spec.camera.height]
    if list(meta.get("image_size", [])) != size:
        raise DatasetError(f"capture {root}: image_size {meta.get('image_size')} differs from its sensor's camera "
                           f"{size}; a replay renders at the sensor's camera size")
    records = read_samples(root)
    if not records:
        raise DatasetError(f"capture {root} holds no samples (samples.jsonl is empty or missing)")
    tasks = []
    for line, record in enumerate(records, start=1):
        where = f"capture {root}: sample {record['id']} (samples.jsonl line {line})"
        index = record.get("tap_index")
        if isinstance(index, bool) or not isinstance(index, int) or not 0 <= index < len(protocol.taps):
            raise DatasetError(f"{where}: tap_index {index!r} is not a tap of protocol.json "
                               f"(0 to {len(protocol.taps) - 1})")
        tap = protocol.taps[index]
        if record.get("object") != tap.object or record["id"] != sample_id(tap.index, tap.object):
            raise DatasetError(f"{where}: object {record.get('object')!r} and id {record['id']!r} disagree with "
                               f"protocol.json tap {index} ({tap.object!r}, id {sample_id(tap.index, tap.object)})")
        tasks.append(PosedTap(tap, _pose(record, where)))
    return Capture(root, meta, protocol_dict, spec, tuple(records), tuple(tasks))


def select(capture: Capture, ids: Sequence[str] | None) -> list[PosedTap]:
    """The tasks of the samples ``ids`` (all when None), in the capture's order."""
    if ids is None:
        return list(capture.tasks)
    known = set(capture.ids)
    unknown = [i for i in ids if i not in known]
    if unknown:
        raise ValueError(f"ids must be samples of {capture.root}, got unknown {unknown[:5]}")
    wanted = set(ids)
    return [t for t, sid in zip(capture.tasks, capture.ids) if sid in wanted]


def replay(
    capture: str | Path | Capture,
    out: str | Path,
    renderer: RendererPlugin,
    options: dict | None = None,
    ids: Sequence[str] | None = None,
    workers: int = 1,
    progress: bool = True,
    executor: str = "local",
    address: str | None = None,
) -> dict:
    """Render a capture's samples at their measured poses into the dataset ``out``
    (resumable); returns ``generate``'s summary.

    Parameters
    ----------
    capture : the capture folder (or ``read_capture``'s result).
    renderer, options : the renderer plugin (``scenes.renderers.RendererPlugin``, e.g. the
        module ``phong_reference.plugin``; the command line's ``get_renderer``) and its
        options, as ``tactile-sim dataset``.
    ids : only these samples (default all).

    ``out`` gets the capture's protocol.json unchanged (so its sha256 is the capture's),
    its protocol summary, its sensor and its sample ids; ``dataset.json`` also records
    ``replay``: the capture it came from and the pose key it replayed.
    """
    renderer = check_plugin(renderer)
    capture = capture if isinstance(capture, Capture) else read_capture(capture)
    tasks = select(capture, ids)
    summary = {k: v for k, v in (capture.meta.get("protocol") or {}).items() if k not in ("file", "sha256")}
    meta = {"source": None, "protocol": summary,
            "replay": {"capture": str(capture.root.resolve()), "pose": POSE_KEY}}
    from .indenters import indenter

    for name in capture.objects:
        indenter(name)  # unknown names fail here, before any work
    # No protocol_checks.validate: the poses are where the rig went, not where it was told to go;
    # a pose outside the rig's travel fails when it is set, naming its sample.
    return run_tasks(out, capture.spec, tasks, capture.objects, capture.protocol, meta, renderer, options,
                     workers=workers, progress=progress, executor=executor, address=address)
