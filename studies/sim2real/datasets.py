"""The study's datasets besides the capture, each cached under ``DIR`` and resumed: the fast
path's replays of the capture by light field, their gaps to it, the gap diagnosis, and the
simulated protocols.

- ``DIR/replay_<field>``: the capture replayed at its measured poses (``scenes.replay``)
  by the fast path (``phong_reference.plugin``) with the field and the capture's
  background;
- ``DIR/diagnosis``: the gap diagnosis of the capture against a replay
  (``studies.gap.diagnose.run``): the effects to add, fitted;
- ``DIR/sim_<protocol>_<field>``: a protocol rendered by the study's compact fast path
  (``studies.sim2real.plugin``) with the capture's background.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np

from phong_reference import plugin as phong
from scenes.body import checked_membrane
from scenes.protocol import make_protocol
from scenes.dataset import read_meta, read_samples
from scenes.generate import generate
from scenes.replay import read_capture, replay
from studies.gap.diagnose import run as diagnose

from . import data, plugin
from .plan import Settings


def complete(root: Path, taps: int | None = None) -> bool:
    """Whether a dataset folder holds all its protocol's taps."""
    if not (root / "dataset.json").exists():
        return False
    want = read_meta(root)["protocol"]["taps"] if taps is None else taps
    return len(read_samples(root)) >= want


def ensure_replays(out: Path, real: Path, fields: tuple[str, ...], workers: int, progress: bool) -> dict[str, Path]:
    """The fast path's replay of the capture ``real`` with each light field, into
    ``DIR/replay_<field>``."""
    capture = read_capture(real)
    replays = {}
    for f in fields:
        root = out / f"replay_{f}"
        if not complete(root, len(capture.records)):
            replay(capture, root, phong, {"field": f, "background": str(real / "background.png")}, workers=workers,
                   progress=progress)
        replays[f] = root
    return replays


def field_gaps(real: data.Arrays, replays: dict[str, data.Arrays], mask: np.ndarray) -> dict:
    """Each replay's MAE to the capture over the image circle, per sample then averaged,
    at the arrays' resolution ([0, 1] units)."""
    out = {}
    for f, sim in replays.items():
        sim = data.aligned(sim, real.ids, f"the {f} replay")
        diff = np.abs(sim.images.astype(np.float32) - real.images.astype(np.float32)) / 255.0
        out[f] = float(diff[:, mask].mean())
    return out


def ensure_diagnosis(out: Path, real: Path, sim: Path, options: dict, progress: bool) -> dict:
    """The gap diagnosis of the capture ``real`` against its replay ``sim`` into
    ``DIR/diagnosis``: its report.json. options : keywords of ``studies.gap.diagnose.run``
    (e.g. ``effects``, ``intervals``)."""
    where = out / "diagnosis"
    if not (where / "report.json").exists():
        diagnose(real, sim, where, progress=progress, **options)
    return json.loads((where / "report.json").read_text())


def ensure_sim(out: Path, name: str, field_name: str, background: Path, settings: Settings, spec,
               objects: tuple[str, ...], progress: bool) -> Path:
    """A simulated protocol of ``objects`` into ``DIR/sim_<name>_<field>``."""
    root = out / f"sim_{name}_{field_name}"
    protocol = make_protocol(name, spec, checked_membrane(spec), objects, seed=0)
    if name == "extended" and settings.extended_taps is not None and settings.extended_taps < len(protocol.taps):
        keep = np.sort(np.random.default_rng(0).choice(len(protocol.taps), settings.extended_taps, replace=False))
        protocol = replace(protocol, taps=tuple(protocol.taps[i] for i in keep))
    if not complete(root, len(protocol.taps)):
        generate(root, spec, protocol, renderer=plugin,
                 options={"field": field_name, "background": str(background), "depth_factor": settings.factor},
                 workers=settings.workers, progress=progress)
    return root
