"""A sensor profile: what calibration against a real unit fitted, as plain data (TOML).

``tactile-sim calibrate`` writes one (``profile.toml``); every command that renders takes
it with ``--profile PATH``. It is read here, in ``scenes``, so that no renderer imports
another: each renderer applies the tables it knows.

Tables (all lengths in the camera's pixels at its full resolution, angles in radians):

- ``sensor``: the spec's name and LED names; a profile is refused for another sensor.
- ``alignment``: the real camera against the spec's (``align_image``): ``scale`` times
  its focal length, ``shift_px`` (u, v) its principal point moved, ``distortion`` (k1, k2)
  its lens' own (absent: the spec's; ``scenes.camera.lens_radius``), ``rotation_rad`` the
  membrane and LEDs turned about the optical axis (the image circle, which belongs to
  the lens, stays), and
  ``led_azimuth_rad``, each LED's turn about the sensor's axis from the spec's position
  (``Profile.sensor_spec`` moves the LEDs, so contacts stay where they are).
- ``camera``: the real camera's response, applied to a linear render L (per channel c)::

      image_c = clip((V(r) L_c + offset_c) ** (1 / gamma), 0, saturation_c)

  with V(r) = 1 + vignetting[0] r^2 + vignetting[1] r^4, r the distance from the image
  circle's centre over its radius; ``image_circle`` (cx, cy, radius) or none where the
  optics fill the frame (pixels outside it are 0).
- ``reference``: the physically based reference's fitted effects (``effects``, names of
  pbr_tactile.effects.Effects), each source's RGB gain (``sources``, ``gains``: the
  film's response times the source's power, rows in source order).
- ``phong``: the fast path's constants: its background term (``background``, a smooth
  model in the image circle's polar coordinates, ``phong_reference.background``) and the
  ambient weight k_a i_a that multiplies it.
- ``fit``: how the profile was fitted (data, held-out R^2, intervals, converged).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from .camera import Camera, project
from .spec import DISTORTION_BOUND, SensorSpec
from .spec_read import read_toml

#: Bump when the meaning of a table changes; older profiles are refused.
PROFILE_VERSION = 2
#: Physical bounds of the camera table.
GAMMA_RANGE = (0.3, 4.0)
SCALE_RANGE = (0.5, 2.0)


@dataclass(frozen=True)
class CameraProfile:
    """The real camera's response (see the module doc); the identity by default."""

    gamma: float = 1.0
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    saturation: tuple[float, float, float] = (1.0, 1.0, 1.0)
    vignetting: tuple[float, float] = (0.0, 0.0)
    image_circle: tuple[float, float, float] | None = None

    def __post_init__(self):
        if not (GAMMA_RANGE[0] <= self.gamma <= GAMMA_RANGE[1]):
            raise ValueError(f"profile camera.gamma must be in [{GAMMA_RANGE[0]}, {GAMMA_RANGE[1]}], got {self.gamma}")
        _vector(self.offset, 3, "camera.offset", lo=0.0, hi=1.0)
        _vector(self.saturation, 3, "camera.saturation", lo=1e-3, hi=1.0)
        _vector(self.vignetting, 2, "camera.vignetting")
        if self.image_circle is not None:
            cx, cy, radius = _vector(self.image_circle, 3, "camera.image_circle")
            if not radius > 0:
                raise ValueError(f"profile camera.image_circle radius must be > 0 px, got {radius}")
        if np.min(self.falloff(np.linspace(0.0, 1.0, 101))) < 0:
            raise ValueError(f"profile camera.vignetting {self.vignetting} makes the lens' relative illumination "
                             "negative inside the image circle")

    def falloff(self, r: np.ndarray) -> np.ndarray:
        """V(r), r the radius over the image circle's."""
        return relative_illumination(self.vignetting, r)


def relative_illumination(vignetting: tuple[float, float], r: np.ndarray) -> np.ndarray:
    """The lens' V(r) = 1 + a1 r^2 + a2 r^4 for vignetting (a1, a2), r the radius over
    the image circle's."""
    a1, a2 = vignetting
    return 1.0 + a1 * r**2 + a2 * r**4


@dataclass(frozen=True)
class Alignment:
    """The membrane image against the spec's camera (see the module doc): the real
    camera is the spec's with its focal length times ``scale``, its principal point moved
    by ``shift_px`` and, where given, its lens' ``distortion`` (k1, k2; None: the spec's),
    the membrane turned by ``rotation_rad`` about the optical axis."""

    rotation_rad: float = 0.0
    scale: float = 1.0
    shift_px: tuple[float, float] = (0.0, 0.0)
    #: Each LED's turn about the sensor's axis (rad), in the spec's LED order; () none.
    led_azimuth_rad: tuple[float, ...] = ()
    distortion: tuple[float, float] | None = None

    def __post_init__(self):
        if not (math.isfinite(self.rotation_rad) and SCALE_RANGE[0] <= self.scale <= SCALE_RANGE[1]):
            raise ValueError(f"profile alignment: rotation_rad must be finite and scale in {list(SCALE_RANGE)}, got "
                             f"{self.rotation_rad} and {self.scale}")
        _vector(self.shift_px, 2, "alignment.shift_px")
        _vector(self.led_azimuth_rad, len(self.led_azimuth_rad), "alignment.led_azimuth_rad", lo=-math.pi, hi=math.pi)
        if self.distortion is not None:
            _vector(self.distortion, 2, "alignment.distortion", lo=-DISTORTION_BOUND, hi=DISTORTION_BOUND)

    def lens(self, camera: Camera) -> Camera:
        """The real camera this alignment says ``camera`` (the spec's) is."""
        k1, k2 = (camera.k1, camera.k2) if self.distortion is None else self.distortion
        return dataclasses.replace(camera, f=camera.f * self.scale, cx=camera.cx + self.shift_px[0],
                                   cy=camera.cy + self.shift_px[1], k1=float(k1), k2=float(k2))

    def sampling(self, shape: tuple[int, int], camera: Camera, rotation_rad: float | None = None,
                 rendered: Camera | None = None, slopes: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
        """(2, h, w) where each pixel of an aligned image at ``shape`` samples the spec's
        image (rows, columns; for scipy.ndimage.map_coordinates): its ray through the real
        camera (``lens`` of ``camera``, the spec's at its full resolution), turned back by
        the rotation (``rotation_rad``, default this alignment's) about the optical axis,
        projected through ``rendered`` (the camera the image was taken with; default
        ``camera``). NaN-free: a pixel no ray reaches samples far outside. ``slopes``:
        the real camera's rays at ``shape`` (``Camera.slopes``), where already known."""
        h, w = shape
        x, y = self.lens(camera).scaled(w, h).slopes() if slopes is None else slopes
        a = self.rotation_rad if rotation_rad is None else rotation_rad
        c, sn = math.cos(a), math.sin(a)
        turned = np.stack([c * x + sn * y, -sn * x + c * y, np.ones_like(x)], axis=-1)
        uv = project(turned, (rendered or camera).scaled(w, h))
        return np.nan_to_num(np.stack([uv[..., 1], uv[..., 0]]), nan=-1e6)

    def moved(self, u: np.ndarray, v: np.ndarray, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
        """Where points (u, v) of the spec's image (``camera``'s pixels) appear in the
        aligned image: the forward map that ``sampling`` inverts."""
        x, y = camera.slopes(np.asarray(u, np.float64), np.asarray(v, np.float64))
        c, s = math.cos(self.rotation_rad), math.sin(self.rotation_rad)
        uv = project(np.stack([c * x - s * y, s * x + c * y, np.ones_like(x)], axis=-1), self.lens(camera))
        return uv[..., 0], uv[..., 1]


@dataclass(frozen=True)
class Profile:
    """A calibrated sensor (see the module doc)."""

    sensor: str
    leds: tuple[str, ...]
    alignment: Alignment = field(default_factory=Alignment)
    camera: CameraProfile = field(default_factory=CameraProfile)
    reference: dict = field(default_factory=dict)
    phong: dict = field(default_factory=dict)
    fit: dict = field(default_factory=dict)

    def check(self, spec: SensorSpec) -> Profile:
        """This profile, if it was fitted for ``spec``; else a ValueError saying why."""
        names = tuple(led.name for led in spec.leds)
        if self.sensor != spec.name or tuple(self.leds) != names:
            raise ValueError(f"the profile is for sensor {self.sensor!r} with LEDs {list(self.leds)}, not for "
                             f"{spec.name!r} with LEDs {list(names)}: calibrate this sensor, or pass its spec")
        return self

    def sensor_spec(self, spec: SensorSpec) -> SensorSpec:
        """``spec`` as this unit is built: each LED (position and direction) turned about
        the camera's axis by its ``alignment.led_azimuth_rad`` and the camera's image
        circle the profile's. Renderers render this spec, then ``align_image``."""
        self.check(spec)
        turns = self.alignment.led_azimuth_rad or (0.0,) * len(spec.leds)
        if len(turns) != len(spec.leds):
            raise ValueError(f"profile alignment.led_azimuth_rad has {len(turns)} values for {len(spec.leds)} LEDs")
        spec = turn_leds(spec, turns)
        camera = spec.camera
        circle = self.camera.image_circle
        if circle is not None:
            camera = dataclasses.replace(camera, mask_center_px=(float(circle[0]), float(circle[1])),
                                         mask_radius_px=float(circle[2]))
        return spec.replace(camera=camera)

    def to_dict(self) -> dict:
        out = {"version": PROFILE_VERSION, "sensor": {"name": self.sensor, "leds": list(self.leds)},
               "alignment": asdict(self.alignment), "camera": asdict(self.camera)}
        if self.camera.image_circle is None:
            del out["camera"]["image_circle"]
        for name in ("reference", "phong", "fit"):
            if getattr(self, name):
                out[name] = getattr(self, name)
        return _plain(out)


def turn_leds(spec: SensorSpec, azimuths) -> SensorSpec:
    """``spec`` with each LED (position and direction) turned about the camera's axis by
    its azimuth, radians."""
    if len(azimuths) != len(spec.leds):
        raise ValueError(f"{len(azimuths)} azimuths for {len(spec.leds)} LEDs")
    return spec.replace(leds=tuple(dataclasses.replace(led, position=_turn(led.position, a),
                                                       direction=_turn(led.direction, a))
                                   for led, a in zip(spec.leds, azimuths)))


def _turn(v, angle: float) -> tuple[float, float, float]:
    """A 3-vector turned by ``angle`` about the camera's z axis."""
    c, s = math.cos(angle), math.sin(angle)
    return (c * v[0] - s * v[1], s * v[0] + c * v[1], float(v[2]))


def align_image(image: np.ndarray, alignment: Alignment, camera: Camera, fill: float = 0.0) -> np.ndarray:
    """(h, w[, C]) an image of the spec's membrane -> as the real camera sees it: turned,
    scaled and shifted by ``alignment`` about the principal point of ``camera`` (the
    spec's, full resolution; the image may be smaller), bilinear; ``fill`` where it
    samples outside the image."""
    from scipy import ndimage

    image = np.asarray(image)
    coords = alignment.sampling(image.shape[:2], camera)
    if image.ndim == 2:
        return ndimage.map_coordinates(image, coords, order=1, mode="constant", cval=fill)
    return np.stack([ndimage.map_coordinates(image[..., c], coords, order=1, mode="constant", cval=fill)
                     for c in range(image.shape[2])], axis=-1)


def _vector(value, n: int, name: str, lo: float = -math.inf, hi: float = math.inf) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in value)
    except (TypeError, ValueError):
        values = ()
    if len(values) != n or not all(math.isfinite(v) and lo <= v <= hi for v in values):
        bounds = "" if lo == -math.inf else f" in [{lo:g}, {hi:g}]"
        raise ValueError(f"profile {name} must be {n} finite numbers{bounds}, got {value!r}")
    return values


def _plain(value):
    """numpy scalars and arrays, tuples -> TOML-writable Python values."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items() if v is not None}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [_plain(v) for v in value]
    if isinstance(value, (np.floating, float)):
        return float(value)
    if isinstance(value, (np.integer,)) and not isinstance(value, bool):
        return int(value)
    if isinstance(value, np.bool_):
        return bool(value)
    return value


def write_profile(profile: Profile, path: str | Path) -> Path:
    """Write ``profile`` as TOML, atomically (a temporary file, then a rename)."""
    import tomli_w

    from .files import atomic_write_bytes

    path = Path(path)
    atomic_write_bytes(path, tomli_w.dumps(profile.to_dict()).encode())
    return path


def profile_from_dict(data: dict, where: str = "profile") -> Profile:
    """A Profile from its TOML tables; a ValueError naming what is wrong."""
    if data.get("version") != PROFILE_VERSION:
        raise ValueError(f"{where}: version {data.get('version')!r} is not {PROFILE_VERSION}; re-run tactile-sim "
                         "calibrate")
    try:
        sensor = data["sensor"]
        camera = dict(data.get("camera", {}))
        if "image_circle" in camera:
            camera["image_circle"] = tuple(camera["image_circle"])
        for key in ("offset", "saturation", "vignetting"):
            if key in camera:
                camera[key] = tuple(camera[key])
        alignment = dict(data.get("alignment", {}))
        for key in ("shift_px", "led_azimuth_rad", "distortion"):
            if key in alignment:
                alignment[key] = tuple(alignment[key])
        return Profile(sensor=str(sensor["name"]), leds=tuple(sensor["leds"]), alignment=Alignment(**alignment),
                       camera=CameraProfile(**camera), reference=dict(data.get("reference", {})),
                       phong=dict(data.get("phong", {})), fit=dict(data.get("fit", {})))
    except (KeyError, TypeError) as exc:
        raise ValueError(f"{where}: malformed profile ({exc!r}); expected the tables sensor, alignment, camera, "
                         "reference, fit (see scenes.profile)") from None
    except ValueError as exc:
        raise ValueError(f"{where}: {exc}") from None


def load_profile(path: str | Path, spec: SensorSpec | None = None) -> Profile:
    """Read a profile.toml, checked against ``spec`` when given."""
    path = Path(path)
    data = read_toml(path, "profile")
    profile = profile_from_dict(data, f"profile {path}")
    return profile.check(spec) if spec is not None else profile


def camera_response(linear: np.ndarray, camera: CameraProfile, falloff: np.ndarray | None = None) -> np.ndarray:
    """(H, W, 3) linear image -> the real camera's image in [0, 1] (module doc);
    ``falloff`` (H, W) the lens' V(r) and the image circle (0 outside), None: none."""
    lin = np.asarray(linear, np.float64)
    if falloff is not None:
        lin = lin * falloff[..., None]
    lin = np.clip(lin + np.asarray(camera.offset), 0.0, None)
    if falloff is not None:
        lin = np.where(falloff[..., None] > 0, lin, 0.0)
    return np.minimum(lin ** (1.0 / camera.gamma), np.asarray(camera.saturation))


def circle_polar(circle: tuple[float, float, float] | None, shape: tuple[int, int],
                 full_shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(H, W) each pixel's distance from the image circle's centre over its radius, and
    its azimuth about the centre (rad, atan2 of v and u), at ``shape``; the circle (cx, cy,
    radius) is in pixels of ``full_shape`` (the camera's (H, W)). Without a circle: from
    the frame's centre, over its half diagonal."""
    h, w = shape
    s = h / full_shape[0]
    v, u = np.mgrid[0:h, 0:w]
    if circle is None:
        cx, cy, radius = (full_shape[1] - 1) / 2, (full_shape[0] - 1) / 2, math.hypot(*full_shape) / 2
    else:
        cx, cy, radius = circle
    x, y = u - ((cx + 0.5) * s - 0.5), v - ((cy + 0.5) * s - 0.5)
    return np.hypot(x, y) / (radius * s), np.arctan2(y, x)


def circle_radius(circle: tuple[float, float, float] | None, shape: tuple[int, int],
                  full_shape: tuple[int, int]) -> np.ndarray:
    """(H, W) the radius of ``circle_polar``."""
    return circle_polar(circle, shape, full_shape)[0]


def lens_falloff(camera: CameraProfile, shape: tuple[int, int], full_shape: tuple[int, int]) -> np.ndarray:
    """(H, W) V(r) inside the image circle and 0 outside, at ``shape`` (see
    ``circle_radius``); without a circle nothing is cut."""
    r = circle_radius(camera.image_circle, shape, full_shape)
    inside = r <= 1.0 if camera.image_circle is not None else np.ones(r.shape, bool)
    return np.where(inside, camera.falloff(np.minimum(r, 1.0)), 0.0)
