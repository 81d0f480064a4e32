"""A tiny capture of the rig for tests of replay and compare, made with the fast path.

``write_capture`` lays a capture out as the rig's capture side will
(``docs/dataset-format.md``, ``source: "real"``): per tap the protocol's fields, the
``commanded_pose`` (``Rig.tap_pose``) and the ``measured_pose`` (the commanded one plus a
known perturbation), no depth map, the real no-contact image as background.png, and a
virtual rig's hidden settings in ``virtual.json``, which consumers must not read. Its
images are the fast path's at the measured pose, rendered here through the rig and the
plugin directly (not through ``scenes.generate``'s tasks, which the tests check).

The sensor is the default one at TINY_SIZE, so that a capture takes about a second.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np

#: (width, height) of the tiny camera, px; the image circle scales with it.
TINY_SIZE = (80, 60)
#: Base-protocol taps of the capture, (object, row, position): tip and body of two indenters.
TAPS = (("sphere", 0, 1), ("sphere", 1, 4), ("cylinder", 0, 2), ("cylinder", 2, 4))
#: A known perturbation of the measured pose against the commanded one (metres).
PERTURBATION = {"printer_x": 4e-4, "printer_z": -2e-4}
#: The file of a virtual rig's hidden settings.
HIDDEN = "virtual.json"


def tiny_spec(spec):
    """``spec`` with its camera and image circle at TINY_SIZE (as ``Camera.scaled``)."""
    from scenes.camera import Camera

    small = Camera.from_spec(spec).scaled(*TINY_SIZE)
    centre = None if spec.camera.mask_center_px is None else (small.mask_cx, small.mask_cy)
    return spec.replace(camera=dataclasses.replace(spec.camera, width=small.width, height=small.height,
                                                   mask_radius_px=small.mask_radius_px, mask_center_px=centre))


def capture_protocol(spec, mesh):
    """The capture's protocol: TAPS of the base protocol, indexed 0.."""
    from scenes.protocol import base_protocol

    base = base_protocol(spec, mesh, sorted({o for o, _, _ in TAPS}, key=[o for o, _, _ in TAPS].index))
    chosen = [t for key in TAPS for t in base.taps if (t.object, t.row, t.position) == key]
    return dataclasses.replace(base, taps=tuple(dataclasses.replace(t, index=i) for i, t in enumerate(chosen)))


def write_capture(root: Path, spec, protocol, field: str = "plane", background: str = "solid",
                  perturbation: dict | None = None, alignment=None) -> Path:
    """Write a capture of ``protocol`` rendered by the fast path (``field``,
    ``background``) at the commanded poses plus ``perturbation``; with ``alignment``
    (a scenes.profile.Alignment) the images are moved by it and dataset.json says so."""
    from scenes.camera import Camera
    from scenes.dataset import DatasetWriter, write_sample_files
    from phong_reference import plugin as phong
    from scenes.generate import measured_depth, tap_fields
    from scenes.geometry import membrane_mesh
    from scenes.indenters import indenter
    from scenes.profile import align_image
    from scenes.kinematics import RigLayout
    from scenes.rig import Rig, rig_scene

    perturbation = perturbation or {}
    mesh = membrane_mesh(spec)
    camera = Camera.from_spec(spec)
    rig = Rig(rig_scene(spec, {name: indenter(name) for name in protocol.objects}, membrane=mesh), spec)
    try:
        rig.home()
        ref = rig.depth()
        renderer = phong.make_renderer(spec, mesh, camera, ref, {"field": field, "background": background})
        def moved(image):  # into the "real" camera's frame; its lens' circle stays
            return image if alignment is None else align_image(image, alignment, camera) * camera.mask[..., None]

        meta = {"source": "real", "sensor": dataclasses.asdict(spec),
                "protocol": {"name": protocol.name, "seed": protocol.seed, "taps": len(protocol.taps),
                             "objects": list(protocol.objects)},
                "renderer": {"renderer": "camera", "device": "tests/fake_capture.py"},
                "image_size": [camera.width, camera.height],
                "image": "8-bit RGB PNG of the camera's frame",
                "rig": {"virtual": True, "layout": RigLayout().to_dict()}}
        if alignment is not None:
            meta["alignment"] = {"method": "registration", **dataclasses.asdict(alignment)}
        writer = DatasetWriter(root, meta, protocol.to_dict())
        for tap in protocol.taps:
            rig.mount(tap.object)
            commanded = rig.tap_pose(tap)
            measured = {k: v + perturbation.get(k, 0.0) for k, v in commanded.items()}
            rig.set_joints(**measured)
            depth = rig.depth()
            fields = tap_fields(tap)
            files = write_sample_files(root, fields["id"], moved(renderer.render(depth)), None)
            writer.append({**fields, **files, "commanded_pose": commanded, "measured_pose": measured,
                           "measured_depth": measured_depth(depth, ref, camera, tap, 1e-6)})
        writer.write_background(moved(renderer.no_contact))
    finally:
        rig.close()
    (root / HIDDEN).write_text(json.dumps({"field": field, "background": background,
                                           "perturbation": perturbation}))
    return root


def edit_samples(root: Path, edit) -> None:
    """Rewrite samples.jsonl with ``edit(record) -> record`` applied to each line."""
    path = root / "samples.jsonl"
    lines = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    path.write_text("".join(json.dumps(edit(dict(r))) + "\n" for r in lines))


def images(root: Path, ids=None) -> np.ndarray:
    """(N, H, W, 3) images of a dataset's samples (``ids``, default all, in file order)."""
    from scenes.dataset import load_sample, read_samples

    records = {r["id"]: r for r in read_samples(root)}
    ids = list(records) if ids is None else ids
    return np.stack([load_sample(root, records[i])[0] for i in ids])
