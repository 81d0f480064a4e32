"""The study's "real" data: a capture of the base protocol on the virtual rig, whose camera
is the physically based reference.

The rig's own capture (``rig.capture.capture``: its driver ``rig.session`` over the
printer and servo twins of ``rig.virtual.VirtualRig``) runs the protocol, its camera twin
rendering the rig's depth with the reference (``pbr_tactile.plugin``): the real driver's
code path, as ``tactile-sim rig run --printer twin --servos twin --camera twin --renderer
pbr`` runs it, and a gap to the fast path that is physics, not formulas. dataset.json's
``alignment`` registers the capture's background against the fast path's no-contact image
(``rig.capture.alignment_hook``), as that command's does.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

from phong_reference import plugin as phong
from rig.capture import alignment_hook, capture
from scenes.body import checked_membrane
from scenes.protocol import make_protocol
from scenes.dataset import atomic_write_json, read_samples
from scenes.indenters import INDENTERS
from scenes.renderers import RendererPlugin
from scenes.spec_read import load_spec

from .datasets import complete


def virtual_capture(out: Path, spec, protocol, renderer: RendererPlugin, progress: bool = True) -> dict:
    """``rig.capture.capture`` of ``protocol`` into ``out`` (resumed), its camera twin
    rendering with ``renderer``, the background registered against the fast path's
    (``phong_reference.plugin``); returns the session's summary."""
    return capture(out, spec, protocol, renderer, alignment=alignment_hook(spec, phong, who="studies.sim2real"),
                   progress=progress)


def ensure_capture(out: Path, spec: str | None, progress: bool) -> dict:
    """The reference's capture of the base protocol (all indenters) into ``DIR/real``,
    resumed; returns its one-time cost, kept in ``DIR/capture_cost.json``: the seconds
    spent rendering it and the frames rendered.

    spec : the sensor spec TOML (None: the default sensor)."""
    real = out / "real"
    ledger = out / "capture_cost.json"
    cost = json.loads(ledger.read_text()) if ledger.exists() else {"seconds": 0.0, "frames": 0, "calls": 0}
    if not complete(real):
        before = len(read_samples(real)) if (real / "dataset.json").exists() else 0
        from pbr_tactile import plugin as pbr  # the reference is needed only while it renders

        t0 = time.perf_counter()
        sensor = load_spec(spec)
        virtual_capture(real, sensor, make_protocol("base", sensor, checked_membrane(sensor), INDENTERS), pbr,
                        progress)
        cost = {"seconds": cost["seconds"] + time.perf_counter() - t0,
                "frames": cost["frames"] + len(read_samples(real)) - before, "calls": cost["calls"] + 1}
        atomic_write_json(ledger, cost)
    return {**cost, "what": "wall seconds of the capture's rendering calls made by this study (a capture resumed "
                            "adds up), and the frames they rendered"}
