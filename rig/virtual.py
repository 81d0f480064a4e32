"""The virtual rig: the device twins moving the MuJoCo rig, and a camera that renders it.

The printer twin's moves and the servo twin's angles set the joints of ``scenes.rig.Rig``
(through the layout: printer coordinates are ``head - printer_origin``), so the driver
that talks to them over pseudo-terminals is the one a real rig uses. The camera twin
captures the in-sensor depth there and renders it with the renderer plugin it is given
(``scenes.renderers.RendererPlugin``: the fast path or the physically based reference,
with a profile and effects; the command line chooses it), so a session on the virtual
rig writes a capture dataset with known ground truth.

What the camera twin renders with is hidden from whoever reads the capture: the session
writes it to ``virtual.json`` (:meth:`VirtualRig.hidden`), which neither the diagnosis
nor the comparison reads. That includes the twin's *unit* (``UNIT``): where the sensor
it renders differs from the spec the capture records, as a built sensor differs from its
drawing (a softer membrane, another elastomer, LEDs of another bin).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from scenes.kinematics import RigLayout
from scenes.renderers import RendererPlugin, SharesInputs, build_renderer, check_plugin, plugin_name

#: The dataset ``source`` (scenes.dataset.SOURCES) of the physically based reference's
#: images: its LEDs have powers of their own, and it exposes a capture from its no-contact
#: frame, as an auto-exposed camera does.
REFERENCE_SOURCE = "pbr"

#: What the twin's unit may differ in from the recorded spec, by the physical
#: catalogue's names (``studies.gap.physical``), with what each value means.
UNIT = {
    "membrane_compliance": "imprint depth / commanded depth, in [0.3, 2] (the rendered dent is this times deeper)",
    "layer_spread": "the elastomer's Poisson ratio, in [0, 0.5] (sets the elastic layer's decay length)",
    "led_peak_shift": "nm added to each LED's emission peak: one value for every LED, or one per LED, each in "
                      "[-40, 40]",
    "led_power": "each LED's radiant power relative to the spec's: one value for every LED, or one per LED, each in "
                 "[0.25, 4] (LEDs of another bin; the pbr camera twin only)",
    "camera_gains": "the camera's white balance: a gain per channel (R, G, B), each in [0.25, 4], on the exposed image",
    "alignment": "the camera's seat in the tube: du, dv (px, the image moves right and down) and a turn (rad, about "
                 "the image's centre, clockwise on screen), |shift| <= 40 px, |turn| <= 0.2",
    "blur": "the lens's defocus: the radius of its blur disc in px, in [0, 8]",
}
#: Entries of ``UNIT`` that are the camera's, not the sensor's: they act on the rendered
#: image (``unit_image``), in this order.
CAMERA_UNIT = ("blur", "alignment", "camera_gains")


def _values(name: str, value) -> tuple:
    values = tuple(value) if isinstance(value, (tuple, list)) else (value,)
    if name not in UNIT:
        raise ValueError(f"unit {name!r} is not one the twin can change; it can change: {', '.join(UNIT)}")
    if not values or not all(isinstance(v, (int, float)) and math.isfinite(v) for v in values):
        raise ValueError(f"unit {name} must be finite numbers, got {value!r}")
    return tuple(float(v) for v in values)


def _led_power(spec, values: tuple) -> tuple:
    """Each LED's power of a ``led_power`` entry, checked against ``UNIT``'s range."""
    powers = values * len(spec.leds) if len(values) == 1 else values
    if len(powers) != len(spec.leds) or not all(0.25 <= v <= 4.0 for v in powers):
        raise ValueError(f"unit led_power must be 1 or {len(spec.leds)} powers in [0.25, 4], got {values!r}")
    return powers


def unit_spec(spec, unit: dict):
    """(the spec the twin renders, the compliance it presses with) for ``unit`` (names
    of ``UNIT``; the camera's entries, ``CAMERA_UNIT``, are checked here and applied by
    ``unit_image``); a ValueError naming the entry for anything else."""
    spec_, compliance = spec, 1.0
    for name, value in unit.items():
        values = _values(name, value)
        if name in CAMERA_UNIT:
            _camera_entry(name, values)
        elif name == "led_power":
            _led_power(spec, values)
        elif name == "membrane_compliance":
            if len(values) != 1 or not 0.3 <= values[0] <= 2.0:
                raise ValueError(f"unit membrane_compliance must be one number in [0.3, 2], got {value!r}")
            compliance = values[0]
        elif name == "layer_spread":
            if len(values) != 1 or not 0.0 <= values[0] <= 0.5:
                raise ValueError(f"unit layer_spread (a Poisson ratio) must be one number in [0, 0.5], got {value!r}")
            spec_ = spec_.replace(elastic=dataclasses.replace(spec_.elastic, poisson_ratio=values[0]))
        else:
            shifts = values * len(spec.leds) if len(values) == 1 else values
            if len(shifts) != len(spec.leds) or not all(-40.0 <= v <= 40.0 for v in shifts):
                raise ValueError(f"unit led_peak_shift must be 1 or {len(spec.leds)} shifts in [-40, 40] nm, got "
                                 f"{value!r}")
            if any(led.peak_nm is None for led in spec.leds):
                raise ValueError("unit led_peak_shift needs every LED's peak_nm in the spec")
            spec_ = spec_.replace(leds=tuple(dataclasses.replace(led, peak_nm=led.peak_nm + d)
                                             for led, d in zip(spec_.leds, shifts)))
    return spec_, compliance


def _camera_entry(name: str, values: tuple) -> tuple:
    """``values`` of a camera entry, checked against ``UNIT``'s ranges."""
    if name == "camera_gains":
        ok = len(values) == 3 and all(0.25 <= v <= 4.0 for v in values)
    elif name == "alignment":
        ok = len(values) == 3 and abs(values[0]) <= 40 and abs(values[1]) <= 40 and abs(values[2]) <= 0.2
    else:
        ok = len(values) == 1 and 0.0 <= values[0] <= 8.0
    if not ok:
        raise ValueError(f"unit {name} is {UNIT[name]}; got {values!r}")
    return values


def _disc(radius: float, supersample: int = 8) -> np.ndarray:
    """A defocused lens's point spread: a uniform disc of ``radius`` px, each kernel cell
    weighted by the share of it inside (supersampled), summing to 1."""
    half = int(math.ceil(radius))
    sub = (np.arange(supersample) + 0.5) / supersample - 0.5
    grid = np.arange(-half, half + 1)[:, None] + sub[None, :]
    x = grid.reshape(-1)
    inside = (x[:, None] ** 2 + x[None, :] ** 2 <= radius**2).astype(np.float64)
    n = 2 * half + 1
    kernel = inside.reshape(n, supersample, n, supersample).mean(axis=(1, 3))
    return kernel / kernel.sum()


def unit_image(image: np.ndarray, unit: dict) -> np.ndarray:
    """The camera entries of ``unit`` on a rendered (H, W, 3) image in [0, 1]: the lens's
    defocus (a disc, ``_disc``), then the camera's seat (the picture turned about its centre
    and shifted, linear resampling, edge pixels repeated), then the white balance,
    clipped to [0, 1]. The image is unchanged where ``unit`` has none of them.

    A physical camera, not the diagnosis's image models: a disc, not a Gaussian; the seat
    is a rigid motion of the sensor under the lens (so the image circle moves too)."""
    stages = {name: _camera_entry(name, _values(name, unit[name])) for name in CAMERA_UNIT if name in unit}
    if not stages:
        return image
    from scipy import ndimage

    out = np.asarray(image, np.float64)
    if stages.get("blur", (0.0,))[0] > 0:
        out = ndimage.convolve(out, _disc(stages["blur"][0])[..., None], mode="nearest")  # each channel alone
    if "alignment" in stages:
        du, dv, turn = stages["alignment"]
        h, w = out.shape[:2]
        centre = np.array([(h - 1) / 2, (w - 1) / 2, 0.0])
        c, s = math.cos(turn), math.sin(turn)
        # output (row, col, channel) reads the input at R(-turn) (p - centre - shift) + centre; channels stay
        inverse = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        offset = centre - inverse @ (centre + np.array([dv, du, 0.0]))
        out = ndimage.affine_transform(out, inverse, offset=offset, order=1, mode="nearest")
    if "camera_gains" in stages:
        out = out * np.asarray(stages["camera_gains"])
    return np.clip(out, 0.0, 1.0).astype(np.float32)


class TwinCamera:
    """Renders the MuJoCo rig's in-sensor depth: ``grab() -> (H, W, 3)`` in [0, 1]."""

    def __init__(self, virtual: VirtualRig):
        self._virtual = virtual
        self.frames = 0

    def settle(self) -> None:
        """Nothing to wait for: the joints are set before the printer's ``ok``."""

    def grab(self) -> np.ndarray:
        renderer = self._virtual.renderer()
        with self._virtual.lock:
            depth = np.asarray(self._virtual.rig.depth(), np.float32)
        self.frames += 1
        if self._virtual.compliance != 1.0:  # the unit's membrane gives more (or less) than commanded
            ref = self._virtual.ref_depth
            depth = (ref - self._virtual.compliance * (ref - depth)).astype(np.float32)
        from scenes.generate import render_sample

        image = np.asarray(render_sample(renderer, depth)["image"], np.float32)
        return unit_image(image, self._virtual.unit)  # the unit's own camera, if it differs

    def describe(self) -> dict:
        cam = self._virtual.rig.spec.camera
        # The reference sets a capture's exposure from its no-contact frame (its rule), as
        # an auto-exposed camera does, unless a profile's camera sets the image (its gains
        # and response, pbr_tactile.plugin); the fast path has no exposure.
        auto = self._virtual.plugin.SOURCE == REFERENCE_SOURCE and self._virtual.options.get("profile") is None
        return {"kind": "twin", "size": [cam.width, cam.height], "exposure": "auto" if auto else "fixed"}

    def close(self) -> None:
        pass


class VirtualRig:
    """Printer and servo twins on ptys driving a MuJoCo rig, and its camera twin.

    Parameters
    ----------
    spec : SensorSpec.
    objects : the indenters the session uses.
    renderer : the camera twin's renderer plugin (``scenes.renderers.RendererPlugin``, e.g.
        the module ``phong_reference.plugin``; the command line's ``get_renderer``).
    options : that renderer's options (e.g. ``{"profile": PATH, "effects": {...}}``).
    printer_faults, servo_faults : rig.twins faults to inject.
    unit : how the sensor the camera twin renders differs from ``spec`` (``UNIT``).
    """

    def __init__(self, spec, objects, renderer: RendererPlugin, options: dict | None = None,
                 layout: RigLayout = RigLayout(), printer_faults=None, servo_faults=None, unit: dict | None = None):
        import threading

        from scenes.geometry import membrane_mesh
        from scenes.indenters import indenter
        from scenes.rig import Rig, rig_scene

        from .twins.printer import PrinterTwin
        from .twins.servos import ServoTwin

        self.spec, self.layout = spec, layout
        self.unit = dict(unit or {})
        self.unit_spec, self.compliance = unit_spec(spec, self.unit)
        self.ref_depth = None
        self.plugin, self.options = check_plugin(renderer), dict(options or {})
        if "led_power" in self.unit:  # the reference renders each LED's power; the fast path's LEDs have only colours
            if self.plugin.SOURCE != REFERENCE_SOURCE:
                raise ValueError(f"unit led_power needs the pbr camera twin (--renderer pbr); got "
                                 f"{plugin_name(self.plugin)}, whose LEDs have a colour but no power of their own")
            self.options["led_power"] = list(_led_power(spec, _values("led_power", self.unit["led_power"])))
        self.mesh = membrane_mesh(spec)
        self.rig = Rig(rig_scene(spec, {name: indenter(name) for name in objects}, membrane=self.mesh), spec, layout)
        self.lock = threading.Lock()
        self._renderer = None
        self._settings = None
        self.printer = PrinterTwin(printer_faults, on_move=self._on_move)
        self.servos = ServoTwin(servo_faults, on_angles=self._on_angles)
        self.camera = TwinCamera(self)

    # -- the twins move the rig -----------------------------------------------------

    def _on_move(self, position_m: np.ndarray) -> None:
        x, y, z = self.layout.head_position(position_m)
        with self.lock:
            self.rig.set_joints(printer_x=x, printer_y=y, printer_z=z)

    def _on_angles(self, roll: float, pitch: float) -> None:
        with self.lock:
            self.rig.set_joints(sensor_roll=roll, indenter_pitch=pitch)

    def mount(self, name: str) -> None:
        with self.lock:
            self.rig.mount(name)

    # -- the camera's renderer --------------------------------------------------------

    def renderer(self):
        """The camera twin's renderer, built on first use against the no-contact depth."""
        if self._renderer is None:
            from scenes.camera import Camera

            plugin = self.plugin
            spec = self.unit_spec  # the unit's membrane and LEDs (its camera and shape are the spec's)
            camera = Camera.from_spec(spec)
            self._settings = plugin.prepare(spec, self.mesh, camera, self.options)
            with self.lock:
                joints = {name: self.rig.qpos(name) for name in ("printer_x", "printer_y", "printer_z")}
                mounted = self.rig.mounted
                self.rig.set_joints(printer_x=self.layout.home[0], printer_y=self.layout.home[1],
                                    printer_z=self.layout.home[2])
                self.ref_depth = self.rig.depth()
                self.rig.set_joints(**joints)
                self.rig.mount(mounted)
            shared = plugin.shared(spec, self.mesh, camera, self.options) if isinstance(plugin, SharesInputs) else None
            self._renderer = build_renderer(plugin.make_renderer, spec, self.mesh, camera, self.ref_depth,
                                            self.options, shared)
        return self._renderer

    def hidden(self) -> dict:
        """What the camera twin renders with (for ``virtual.json``): ``renderer`` is the name
        its settings give (``scenes.renderers``: ``prepare``)."""
        self.renderer()
        return {"renderer": self._settings.get("renderer"), "options": self.options, "settings": self._settings,
                "unit": self.unit}

    def close(self) -> None:
        for part in (self.printer, self.servos):
            part.close()
        self.rig.close()

    def __enter__(self) -> VirtualRig:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
