"""Capture a tapping protocol on the virtual rig, and align a capture's background.

``capture`` runs the rig's own driver (``rig.session``) over the printer and servo twins
of ``rig.virtual.VirtualRig``, whose camera twin renders with the renderer plugin it is
given: what ``tactile-sim rig run --printer twin --servos twin --camera twin`` runs, and
what a study's virtual capture runs. ``alignment_hook`` is the session's
``after_background`` of any capture, real or virtual: dataset.json's ``alignment`` of the
background against the fast path's no-contact image (``rig.align.capture_alignment``).

The rig imports no renderer: the caller passes in both the camera twin's plugin and the
fast path's (``background``), as the command line looks them up by name.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path

import numpy as np

from scenes.kinematics import RigLayout
from scenes.renderers import RendererPlugin

#: What dataset.json's ``rig`` says of a capture on the twins.
TWINS = {"virtual": True, "printer": "twin", "servos": "twin"}


def sim_background(spec, background: RendererPlugin, shape: tuple[int, int] | None = None) -> np.ndarray:
    """(H, W, 3) float in [0, 1], the no-contact image of ``spec`` by the fast path's plugin
    ``background`` with its solid background (the fast path alone draws no membrane), at
    ``shape`` (H, W; None: the camera's size): what a capture's background is registered
    against."""
    from scenes.body import checked_membrane
    from scenes.camera import Camera, reference_depth

    mesh, camera = checked_membrane(spec), Camera.from_spec(spec)
    options = {"background": "solid"}
    background.prepare(spec, mesh, camera, options)
    image = background.make_renderer(spec, mesh, camera, reference_depth(mesh, camera)[0], options).no_contact
    if shape is not None and image.shape[:2] != tuple(shape):
        from skimage.transform import resize

        image = resize(image, tuple(shape), order=1, anti_aliasing=True)
    return image


def alignment_hook(spec, background: RendererPlugin | None, profile: str | None = None,
                   who: str = "tactile-sim rig run") -> Callable[[np.ndarray], dict]:
    """A session's ``after_background``: dataset.json's alignment between the captured
    background and the simulated images (the profile's when one is given, else a
    registration against ``sim_background`` by the plugin ``background``), or why there is
    none (a registration that finds nothing to hold on to stops no capture; ``who`` names
    the caller in its warning)."""

    def hook(frame: np.ndarray) -> dict:
        from .align import capture_alignment

        if profile:
            from scenes.profile import load_profile

            return {"alignment": capture_alignment(frame, spec, profile=load_profile(profile, spec))}
        try:
            return {"alignment": capture_alignment(frame, spec,
                                                   sim_background=sim_background(spec, background, frame.shape[:2]))}
        except ValueError as exc:
            print(f"{who}: warning: no alignment: {exc}", file=sys.stderr)
            return {"alignment_error": str(exc)}

    return hook


def capture(out: Path, spec, protocol, renderer: RendererPlugin, options: dict | None = None,
            layout: RigLayout | None = None, unit: dict | None = None,
            alignment: Callable[[np.ndarray], dict] | None = None, progress: bool = True) -> dict:
    """Run ``protocol`` on the virtual rig into the capture ``out`` (resumed), its camera
    twin rendering with ``renderer`` and ``options`` as the twin ``unit``; returns the
    session's summary.

    alignment : the session's ``after_background`` (``alignment_hook``; None: no alignment).
    """
    from .marlin import DEFAULT_BAUD as PRINTER_BAUD, MarlinPrinter
    from .servos import DEFAULT_BAUD as SERVO_BAUD, ServoBoard
    from .session import Devices, prepare
    from .virtual import VirtualRig

    layout = RigLayout() if layout is None else layout
    session = prepare(out, spec, protocol, layout, source_meta={"rig": dict(TWINS)}, after_background=alignment)
    with ExitStack() as stack:
        rig = stack.enter_context(VirtualRig(spec, protocol.objects, renderer, options or {}, layout,
                                             unit=unit or {}))
        session.hidden = rig.hidden()
        printer = stack.enter_context(MarlinPrinter(rig.printer.port, PRINTER_BAUD))
        servos = stack.enter_context(ServoBoard(rig.servos.port, SERVO_BAUD))
        return session.run(Devices(printer, servos, rig.camera, rig.mount, 0.0), progress=progress)
