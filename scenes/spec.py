"""Sensor specification: what a sensor is, in SI units, as frozen dataclasses.

A spec is read from one TOML file (or a chain of them) by ``scenes.spec_read``
(``load_spec``, ``spec_from_dict``), which checks each table; the limits it checks
against are here.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .shapes import TABLE_KEYS, family

#: The shipped sensors' folder, and the default: the published simulation's GelTip.
SENSORS_DIR = Path(__file__).with_name("sensors")
DEFAULT_SPEC_PATH = SENSORS_DIR / "geltip.toml"

#: Largest plausible sensor dimension in metres; anything larger is a unit mistake.
MAX_SENSOR_SIZE_M = 1.0
#: Thickness of the glass tube's wall under the membrane, m (``membrane.glass_wall``'s
#: default): the tube's inner radius is ``membrane.core_radius`` less this.
GLASS_WALL_M = 2.0e-3
#: The glass' refractive index (``membrane.glass_ior``'s default): borosilicate.
GLASS_IOR = 1.49
#: Refractive indices a spec may state for the glass.
GLASS_IOR_BOUNDS = (1.3, 2.0)
#: The camera's vertical field of view, rad, and each radial distortion coefficient's
#: magnitude: the range a spec (and a calibration) may state.
FOV_Y_BOUNDS = (math.radians(10.0), math.radians(170.0))
DISTORTION_BOUND = 1.0
#: The camera's tilt off the tube's axis, rad, at most about either axis: beyond it the
#: lens would sit in the tube's wall rather than look along it.
TILT_BOUND_RAD = math.radians(15.0)
#: The elastomer's thickness a spec may state by default, metres (``membrane.thickness_bounds``):
#: under 0.5 mm a 2 mm tap would press on the glass, over 10 mm it is no membrane.
THICKNESS_BOUNDS_M = (0.5e-3, 10.0e-3)
#: Where an LED's light may enter the sensor (``LED.entry``; ``scenes.layout``):
#: "beside" the membrane's base, in the elastomer at its edge; the glass' "edge" (a flat
#: sensor's support plate's rim, a tube's wall's foot), through which it is guided by
#: total internal reflection; or from the air "under" the glass (under a plate, inside a
#: tube), where the LED sits, through the glass.
LED_ENTRIES = ("beside", "edge", "under")


@dataclass(frozen=True)
class MembraneSpec:
    """Outer membrane surface and the glass core under it (``scenes.body``).

    shape : its shape family's name (``scenes.shapes.FAMILIES``): "capsule" (cylinder +
        hemispherical tip, built from ``radius``, ``cylinder_length`` and ``core_radius``),
        "thumb" or "paw" (built from ``params``), "pad" (a flat sensor's domed elastomer
        disc on a clear plate, from ``params``), each seated by the camera's ``offset_m``
        and ``tilt_rad``; or "mesh" (read from ``mesh_path`` in ``mesh_units``, placed in
        the camera frame by ``mesh_transform``).
    thickness : the elastomer's thickness, metres, where the core is derived by offsetting
        the membrane inwards (every family whose body is not known in closed form, unless
        ``core_mesh_path`` gives the core); a capsule's is ``radius - core_radius``.
    core_mesh_path : the glass core's outer surface as a mesh file (``mesh`` only), in the
        membrane's units and frame.
    thickness_bounds : (min, max) metres the elastomer's thickness must stay within
        everywhere.
    """

    shape: str = "capsule"
    radius: float = 0.0115  # m
    cylinder_length: float = 0.044  # m
    base_z: float = -0.010  # m, in the camera frame
    core_radius: float = 0.009  # m
    mesh_edge: float = 0.0005  # m
    mesh_path: str | None = None
    glass_wall: float = GLASS_WALL_M  # m, the glass tube's wall under the membrane
    glass_ior: float = GLASS_IOR  # -, its refractive index
    params: tuple[tuple[str, float], ...] = ()  # a shape family's parameters (scenes.shapes), SI units
    thickness: float | None = None  # m, the elastomer's thickness over a derived core
    core_mesh_path: str | None = None  # the core's mesh file (shape "mesh")
    mesh_units: str = "m"  # "m" or "mm", of mesh_path and core_mesh_path
    mesh_transform: tuple[float, ...] | None = None  # 16 numbers, row-major 4x4 rigid map: file -> camera frame
    thickness_bounds: tuple[float, float] = THICKNESS_BOUNDS_M  # m, (min, max)

    @property
    def elastomer_thickness(self) -> float | None:
        """The stated thickness, metres: a body known in closed form's (its family's
        ``tube``: a capsule's ``radius - core_radius``), otherwise ``thickness`` (None where
        a core mesh gives it, vertex by vertex)."""
        tube = family(self.shape).tube(self)
        return tube.thickness if tube is not None else self.thickness


#: The membrane's shape where a spec names none.
DEFAULT_SHAPE = MembraneSpec.shape
#: A sensor file's key that names the file it overrides (``read_sensor_file``).
BASE_KEY = "base"
#: Arrays of tables a sensor file merges with its base's entry by entry, by name.
NAMED_ARRAYS = ("leds", "led_groups")


@dataclass(frozen=True)
class CameraSpec:
    """Central camera at the origin looking along +z, planar z-depth: a lens of the
    given projection and radial distortion (``scenes.camera.lens_radius``) whose ray at
    fov_y / 2 from the axis lands half the frame's height from the principal point."""

    width: int = 640  # px
    height: int = 480  # px
    fov_y: float = math.pi / 2  # rad
    mask_radius_px: float = 240.0  # px
    mask_center_px: tuple[float, float] | None = None  # px (u, v); None: the principal point
    principal_point_px: tuple[float, float] | None = None  # px (u, v); None: the frame's centre
    distortion: tuple[float, float] = (0.0, 0.0)  # (k1, k2), see scenes.camera.lens_radius
    projection: str = "pinhole"  # "pinhole" or "fisheye" (scenes.camera.PROJECTIONS)
    #: The camera's seat against the tube: its optical centre's offset (x, y) from the
    #: tube's axis, m, and its optical axis' tilt from the tube's axis, rad, turned about
    #: x then y. The seat along the axis is ``membrane.base_z``. The LEDs sit on the
    #: camera's crown and stay in the camera frame; the tube (membrane, glass) moves.
    offset_m: tuple[float, float] = (0.0, 0.0)
    tilt_rad: tuple[float, float] = (0.0, 0.0)

    def tube_to_camera(self) -> np.ndarray:
        """(4, 4) the rigid map from the tube's frame (its axis along z, the camera's seat
        at the origin) into the camera frame: p_camera = R^T (p_tube - (x, y, 0))."""
        ax, ay = self.tilt_rad
        cx, sx, cy, sy = math.cos(ax), math.sin(ax), math.cos(ay), math.sin(ay)
        rotation = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]]) @ np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
        out = np.eye(4)
        out[:3, :3] = rotation.T
        out[:3, 3] = -rotation.T @ np.array([self.offset_m[0], self.offset_m[1], 0.0])
        return out


@dataclass(frozen=True)
class LED:
    """One LED: a point light whose light is guided along the membrane."""

    name: str
    position: tuple[float, float, float]  # m, camera frame
    direction: tuple[float, float, float]  # unit, emission direction
    colour: tuple[float, float, float]  # linear RGB in [0, 1]
    k_d: float  # diffuse coefficient
    k_s: float  # specular coefficient
    peak_nm: float | None = None  # emission peak wavelength (physically based renderer)
    fwhm_nm: float | None = None  # emission full width at half maximum
    group: str | None = None  # the LEDGroup it belongs to; None for a single LED
    beam_half_angle_rad: float | None = None  # rad, its light leaves within this of ``direction``; None: Lambertian
    entry: str | None = None  # where its light enters (LED_ENTRIES); None: by where it sits (pbr_tactile.scene)


@dataclass(frozen=True)
class LEDGroup:
    """LEDs of one colour and build evenly spaced along an arc of a ring about the
    camera's axis: ``count`` LEDs at the centres of ``count`` equal parts of the arc
    ``arc_span_rad`` wide about ``arc_centre_rad`` (0 is +x, towards +y), so that a
    span of 2 pi is a full ring and one LED sits at the centre. Each aims along +z tilted
    by ``tilt_rad`` away from the axis, outwards in its own radial plane."""

    name: str
    count: int  # -, LEDs in the arc
    arc_centre_rad: float  # rad, azimuth of the arc's middle
    arc_span_rad: float  # rad, in [0, 2 pi]: the arc the LEDs share
    ring_radius: float  # m, distance of each LED from the camera's axis
    height: float  # m, z of the LEDs in the camera frame
    tilt_rad: float  # rad, the aim's angle from +z, outwards
    colour: tuple[float, float, float]  # linear RGB in [0, 1]
    k_d: float
    k_s: float
    peak_nm: float | None = None
    fwhm_nm: float | None = None
    beam_half_angle_rad: float | None = None  # rad, each LED's beam; None: Lambertian
    entry: str | None = None  # where each LED's light enters (LED_ENTRIES); None: by where it sits

    def offsets(self) -> np.ndarray:
        """(count,) each LED's azimuth from the arc's centre, as a share of the span:
        (j + 1/2) / count - 1/2."""
        return (np.arange(self.count) + 0.5) / self.count - 0.5

    def led_at(self, azimuth: float, name: str) -> LED:
        """One LED of this group's build at ``azimuth`` rad."""
        c, s = math.cos(azimuth), math.sin(azimuth)
        t = self.tilt_rad
        return LED(name=name, position=(self.ring_radius * c, self.ring_radius * s, self.height),
                   direction=(math.sin(t) * c, math.sin(t) * s, math.cos(t)), colour=self.colour, k_d=self.k_d,
                   k_s=self.k_s, peak_nm=self.peak_nm, fwhm_nm=self.fwhm_nm, group=self.name,
                   beam_half_angle_rad=self.beam_half_angle_rad, entry=self.entry)

    def leds(self) -> tuple[LED, ...]:
        """The group's LEDs, named ``<name><j>``."""
        return tuple(self.led_at(self.arc_centre_rad + self.arc_span_rad * float(o), f"{self.name}{j}")
                     for j, o in enumerate(self.offsets()))


@dataclass(frozen=True)
class Material:
    """Phong material constants shared by all LEDs."""

    ambient: float = 0.8  # k_a i_a, weight of the background
    shininess: float = 100.0  # alpha
    clamp_specular: bool = True  # clamp R.V at 0 before the power


@dataclass(frozen=True)
class Elastic:
    """The membrane's elasticity: the published model's Gaussian G, in pixels at the
    camera's resolution, and the elastic layer's Poisson ratio (scenes.elastic)."""

    sigma_px: float = 5.0
    radius_px: int = 27
    poisson_ratio: float = 0.5  # -, of the elastomer; sets the layer model's decay length


@dataclass(frozen=True)
class Housing:
    """The unit's housing, as far as it bounds where its LEDs may sit (``scenes.layout``):
    no LED further than ``radius`` from the camera's axis, none nearer the camera than
    ``floor_z`` (camera frame, m). None: not recorded, bounded by the sensor's size alone
    (MAX_SENSOR_SIZE_M)."""

    radius: float | None = None  # m, the housing's inner wall from the camera's axis
    floor_z: float | None = None  # m, camera frame: the housing's floor about the camera


@dataclass(frozen=True)
class SensorSpec:
    """A whole optical tactile sensor."""

    name: str
    membrane: MembraneSpec
    camera: CameraSpec
    leds: tuple[LED, ...]  # every LED: the single ones, then each group's
    material: Material
    elastic: Elastic
    led_groups: tuple[LEDGroup, ...] = ()  # the groups some of ``leds`` were laid out by
    housing: Housing = Housing()  # what bounds where the LEDs may sit

    def digest(self) -> str:
        """Stable hash of every field, for cache keys."""
        blob = json.dumps(dataclasses.asdict(self), sort_keys=True, default=str)
        return hashlib.sha256(blob.encode()).hexdigest()[:16]

    def to_dict(self) -> dict:
        """Every field, as a spec file's tables (``spec_from_dict`` reads it back the same):
        the membrane's table leaves out the keys of other shape families
        (``scenes.shapes.TABLE_KEYS``), and keys left unset are left out."""
        data = dataclasses.asdict(self)
        m = data["membrane"]
        others = [key for key, owner in TABLE_KEYS.items() if owner != self.membrane.shape]
        for key in others + ["params"] * (not m["params"]):
            del m[key]
        data["membrane"] = {k: v for k, v in m.items() if v is not None}
        data["housing"] = {k: v for k, v in data["housing"].items() if v is not None}
        return json.loads(json.dumps(data))  # tuples as lists, as TOML and JSON hold them

    def replace(self, **changes) -> "SensorSpec":
        return dataclasses.replace(self, **changes)

    def at_resolution(self, width: int, height: int) -> "SensorSpec":
        """This sensor with a camera of ``width`` x ``height`` pixels: the same field of view
        and lens; its principal point, image circle and the published smoothing's Gaussian
        (pixels) scaled with it. ValueError for another aspect ratio (the vertical field of
        view is the spec's, so the frame's shape must be the camera's)."""
        c = self.camera
        if not (isinstance(width, int) and isinstance(height, int) and width >= 2 and height >= 2):
            raise ValueError(f"a camera's size must be whole pixels, at least 2x2, got {width!r}x{height!r}")
        if abs(width * c.height - height * c.width) > 1e-9 * width * c.height:
            raise ValueError(f"a {width}x{height} frame has another aspect ratio than the {c.width}x{c.height} "
                             f"camera of sensor {self.name!r}; give a spec whose camera has the frames' aspect")
        s = height / c.height

        def px(point):  # a pixel position: centres at integers, so scale about -0.5
            return None if point is None else tuple((v + 0.5) * s - 0.5 for v in point)

        camera = dataclasses.replace(c, width=width, height=height, mask_radius_px=c.mask_radius_px * s,
                                     mask_center_px=px(c.mask_center_px), principal_point_px=px(c.principal_point_px))
        elastic = dataclasses.replace(self.elastic, sigma_px=self.elastic.sigma_px * s,
                                      radius_px=max(1, int(round(self.elastic.radius_px * s))))
        return self.replace(camera=camera, elastic=elastic)

    def group_of(self, name: str) -> LEDGroup:
        """The LED group called ``name``."""
        for group in self.led_groups:
            if group.name == name:
                return group
        raise KeyError(f"sensor {self.name!r} has no LED group {name!r}")
