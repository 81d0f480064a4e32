"""The LEDs' layout as parameters: where each LED's light enters the sensor, its aim and its beam.

A calibration that fits where the light comes from (``pbr_tactile.layout_fit``) moves each
LED within what its unit's housing allows (``[housing]``, ``scenes.spec.Housing``) and
what its entry means (``scenes.spec.LED_ENTRIES``):

- ``under``: the LED sits in the air under the glass (a flat sensor's support plate; a
  tube's bore), where its ``radius_m`` from the axis, ``azimuth_rad`` and ``height_m``
  (camera frame z) put it, and shines through the glass;
- ``edge``: its light enters the glass' end (the plate's rim, the tube wall's foot) at its
  azimuth and is guided by total internal reflection; where along the end is the body's;
- ``beside``: it sits beside the membrane's base and shines into the elastomer's edge at
  its azimuth; where is the body's.

Every LED also has an aim, ``aim_rad`` from the camera's axis (+z) towards it (0: straight
up at the membrane, pi/2: across, towards the axis), and a beam, ``beam_half_angle_rad``
(None: a Lambertian emitter). Its azimuth is the calibration's image model's to fit (the
rotationally symmetric membrane turns it into an image rotation); here it only places the
LED.

Coordinates are in the tube's frame (``CameraSpec.tube_to_camera``): the membrane's axis
along +z. SI units: metres and radians.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from .spec import LED_ENTRIES, MAX_SENSOR_SIZE_M, SensorSpec

#: The parameters of one LED's layout, in a fit's vector order.
PARAMETERS = ("radius_m", "height_m", "aim_rad", "beam_half_angle_rad")
#: Which of them move the light, per entry: an LED at the glass' edge or beside the
#: elastomer enters where the body is at its azimuth, so only its aim and beam count.
FREE = {"under": PARAMETERS, "edge": ("aim_rad", "beam_half_angle_rad"),
        "beside": ("aim_rad", "beam_half_angle_rad")}
#: The narrowest beam a layout may have, rad (a collimated LED's; a bare die's is pi/2).
MIN_BEAM_RAD = math.radians(5.0)
#: An LED under the glass keeps this far from it, metres: more than the reference's
#: emitter's radius (``pbr_tactile.scene.LED_RADIUS_M``), so that its sphere stays in air.
CLEARANCE_M = 0.5e-3


@dataclass(frozen=True)
class LEDLayout:
    """One LED's layout (module doc): SI units, tube frame."""

    entry: str
    azimuth_rad: float
    radius_m: float
    height_m: float
    aim_rad: float
    beam_half_angle_rad: float | None

    def __post_init__(self):
        if self.entry not in LED_ENTRIES:
            raise ValueError(f"layout entry must be one of {', '.join(LED_ENTRIES)}, got {self.entry!r}")
        for name in ("azimuth_rad", "radius_m", "height_m", "aim_rad"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"layout {name} must be finite, got {getattr(self, name)}")

    def position(self) -> np.ndarray:
        """(3,) the LED's place, tube frame, m."""
        c, s = math.cos(self.azimuth_rad), math.sin(self.azimuth_rad)
        return np.array([self.radius_m * c, self.radius_m * s, self.height_m])

    def direction(self) -> np.ndarray:
        """(3,) its unit aim, tube frame: ``aim_rad`` from +z towards the axis."""
        c, s = math.cos(self.azimuth_rad), math.sin(self.azimuth_rad)
        return np.array([-math.sin(self.aim_rad) * c, -math.sin(self.aim_rad) * s, math.cos(self.aim_rad)])

    def vector(self) -> np.ndarray:
        """(4,) PARAMETERS' values; a Lambertian beam as pi / 2 (the widest a cone may be)."""
        beam = math.pi / 2 if self.beam_half_angle_rad is None else self.beam_half_angle_rad
        return np.array([self.radius_m, self.height_m, self.aim_rad, beam])

    def with_vector(self, values) -> "LEDLayout":
        """This layout with PARAMETERS set from ``values`` (4,)."""
        radius, height, aim, beam = (float(v) for v in values)
        return dataclasses.replace(self, radius_m=radius, height_m=height, aim_rad=aim, beam_half_angle_rad=beam)


def tube_frame(spec: SensorSpec, points) -> np.ndarray:
    """(N, 3) camera-frame points in the tube's frame (``CameraSpec.tube_to_camera``),
    where the glass and membrane have their nominal radii about the z axis."""
    import trimesh

    return trimesh.transform_points(np.reshape(np.asarray(points, np.float64), (-1, 3)),
                                    np.linalg.inv(spec.camera.tube_to_camera()))


def camera_frame(spec: SensorSpec, points) -> np.ndarray:
    """(N, 3) tube-frame points in the camera frame."""
    import trimesh

    return trimesh.transform_points(np.reshape(np.asarray(points, np.float64), (-1, 3)), spec.camera.tube_to_camera())


def layout_of(spec: SensorSpec, entries: tuple[str, ...] | str | None = None) -> tuple[LEDLayout, ...]:
    """Each of the spec's LEDs as a layout, in the tube frame: its entry (``entries``, one
    for all or one per LED; default its own, else ``under`` for an LED under the glass'
    lowest point and ``beside`` otherwise), place and aim (its direction's part across the
    axis' radial plane is dropped)."""
    leds = spec.leds
    if isinstance(entries, str) or entries is None:
        entries = (entries,) * len(leds)
    if len(entries) != len(leds):
        raise ValueError(f"layout_of: {len(entries)} entries for {len(leds)} LEDs")
    positions = tube_frame(spec, [led.position for led in leds])
    rotation = np.linalg.inv(spec.camera.tube_to_camera())[:3, :3]
    low = None
    out = []
    for led, entry, p in zip(leds, entries, positions):
        if entry is None:
            entry = led.entry
        if entry is None:
            low = glass_floor(spec) if low is None else low
            entry = "under" if p[2] <= low - CLEARANCE_M else "beside"
        azimuth = math.atan2(p[1], p[0])
        d = rotation @ np.asarray(led.direction, np.float64)
        inward = -(d[0] * math.cos(azimuth) + d[1] * math.sin(azimuth))
        out.append(LEDLayout(entry, azimuth, float(math.hypot(p[0], p[1])), float(p[2]),
                             math.atan2(inward, d[2]), led.beam_half_angle_rad))
    return tuple(out)


def with_layout(spec: SensorSpec, layout) -> SensorSpec:
    """The spec with each LED laid out by ``layout`` (one ``LEDLayout`` per LED), checked
    (``check_layout``); the LEDs keep their names, colours and spectra. A spec's LED
    groups are laid out as their LEDs: the result has single LEDs."""
    layout = tuple(layout)
    check_layout(spec, layout)
    positions = camera_frame(spec, [p.position() for p in layout])
    rotation = spec.camera.tube_to_camera()[:3, :3]
    leds = tuple(dataclasses.replace(led, position=tuple(map(float, x)), direction=tuple(map(float, rotation @ p.direction())),
                                     beam_half_angle_rad=p.beam_half_angle_rad, entry=p.entry, group=None)
                 for led, p, x in zip(spec.leds, layout, positions))
    return spec.replace(leds=leds, led_groups=())


def glass_floor(spec: SensorSpec) -> float:
    """The lowest z of the glass under the membrane, tube frame, metres: a tube's base (its
    wall stands on it), a plate's underside at its lowest (its rim, under a domed pad)."""
    from .shapes import family

    tube = family(spec.membrane.shape).tube(spec.membrane)
    if tube is not None:
        return float(tube.base_z)
    from .body import sensor_body

    body = sensor_body(spec)
    loop = body.base_loop
    core = np.asarray(body.core.vertices)[loop]
    underside = core - spec.membrane.glass_wall * body.normals[loop]
    return float(tube_frame(spec, underside)[:, 2].min())


def layout_bounds(spec: SensorSpec, entry: str) -> dict[str, tuple[float, float, str]]:
    """Each parameter's (low, high, what sets it) for an LED of ``entry`` in this sensor:
    its distance from the axis within the housing's radius; under the glass, its height
    between the housing's floor and the glass' lowest point less CLEARANCE_M; an aim
    within pi / 2 of the axis; a beam of MIN_BEAM_RAD to pi / 2."""
    if entry not in LED_ENTRIES:
        raise ValueError(f"layout entry must be one of {', '.join(LED_ENTRIES)}, got {entry!r}")
    housing = spec.housing
    outer = (housing.radius, "the housing's radius") if housing.radius is not None else (
        MAX_SENSOR_SIZE_M, "the largest sensor")
    floor = (tube_frame(spec, [0.0, 0.0, housing.floor_z])[0, 2], "the housing's floor") if housing.floor_z is not None \
        else (-MAX_SENSOR_SIZE_M, "the largest sensor")
    top = (glass_floor(spec) - CLEARANCE_M, "the glass' lowest point") if entry == "under" else (
        MAX_SENSOR_SIZE_M, "the largest sensor")
    return {"radius_m": (0.0, outer[0], outer[1]), "height_m": (floor[0], top[0], f"{floor[1]} and {top[1]}"),
            "aim_rad": (-math.pi / 2, math.pi / 2, "an aim within a right angle of the axis"),
            "beam_half_angle_rad": (MIN_BEAM_RAD, math.pi / 2, "a beam of 5 to 90 degrees")}


def check_layout(spec: SensorSpec, layout) -> None:
    """Refuse a layout one of whose parameters lies outside its bound (``layout_bounds``):
    a ValueError of one line naming the LED, the parameter and the bound."""
    layout = tuple(layout)
    if len(layout) != len(spec.leds):
        raise ValueError(f"a layout of sensor {spec.name!r} has one LEDLayout per LED ({len(spec.leds)}), got "
                         f"{len(layout)}")
    for led, p in zip(spec.leds, layout):
        if not isinstance(p, LEDLayout):
            raise ValueError(f"layout of LED {led.name!r}: expected an LEDLayout, got {type(p).__name__}")
        bounds = layout_bounds(spec, p.entry)
        values = dict(zip(PARAMETERS, p.vector()))
        for name in FREE[p.entry] + ("radius_m",):
            low, high, why = bounds[name]
            value = values[name]
            if not low - 1e-12 <= value <= high + 1e-12:
                raise ValueError(f"layout of LED {led.name!r} ({p.entry}): {name} = {value:.6g} is outside "
                                 f"[{low:.6g}, {high:.6g}] ({why})")


def layout_to_dicts(layout) -> list[dict]:
    """A layout as plain data (a profile's ``reference.layout``): one table per LED."""
    return [dataclasses.asdict(p) for p in layout]


def layout_from_dicts(data, spec: SensorSpec, where: str = "layout") -> tuple[LEDLayout, ...]:
    """A layout read back from ``layout_to_dicts``' form for ``spec``'s LEDs, checked
    (``check_layout``); ValueError naming ``where`` and what was expected otherwise."""
    if not isinstance(data, (list, tuple)) or len(data) != len(spec.leds):
        raise ValueError(f"{where} must be a list of one table per LED ({len(spec.leds)}), got {data!r:.80}")
    out = []
    for k, t in enumerate(data):
        try:
            beam = t.get("beam_half_angle_rad")
            out.append(LEDLayout(str(t["entry"]), float(t["azimuth_rad"]), float(t["radius_m"]),
                                 float(t["height_m"]), float(t["aim_rad"]), None if beam is None else float(beam)))
        except (AttributeError, KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"{where}[{k}]: expected entry, azimuth_rad, radius_m, height_m, aim_rad and "
                             f"beam_half_angle_rad, got {t!r:.120} ({exc})") from None
    try:
        check_layout(spec, out)
    except ValueError as exc:
        raise ValueError(f"{where}: {exc}") from None
    return tuple(out)
