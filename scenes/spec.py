"""Sensor specification: one TOML file, SI units, read into frozen dataclasses."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

DEFAULT_SPEC_PATH = Path(__file__).with_name("geltip.toml")

#: Largest plausible sensor dimension in metres; anything larger is a unit mistake.
MAX_SENSOR_SIZE_M = 1.0


@dataclass(frozen=True)
class MembraneSpec:
    """Outer membrane surface.

    shape : "capsule" (cylinder + hemispherical tip, built from the numbers below) or
        "mesh" (loaded from ``mesh_path``, in metres, in the camera frame).
    """

    shape: str = "capsule"
    radius: float = 0.0115  # m
    cylinder_length: float = 0.044  # m
    base_z: float = -0.010  # m, in the camera frame
    core_radius: float = 0.009  # m
    mesh_edge: float = 0.0005  # m
    mesh_path: str | None = None

    @property
    def tip_z(self) -> float:
        """z of the tip apex in the camera frame, metres."""
        return self.base_z + self.cylinder_length + self.radius


@dataclass(frozen=True)
class CameraSpec:
    """Pinhole camera at the origin looking along +z, planar z-depth."""

    width: int = 640  # px
    height: int = 480  # px
    fov_y: float = math.pi / 2  # rad
    mask_radius_px: float = 240.0  # px
    mask_center_px: tuple[float, float] | None = None  # px (u, v); None: the principal point


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
class SensorSpec:
    """A whole optical tactile sensor."""

    name: str
    membrane: MembraneSpec
    camera: CameraSpec
    leds: tuple[LED, ...]
    material: Material
    elastic: Elastic

    def digest(self) -> str:
        """Stable hash of every field, for cache keys."""
        blob = json.dumps(dataclasses.asdict(self), sort_keys=True, default=str)
        return hashlib.sha256(blob.encode()).hexdigest()[:16]

    def replace(self, **changes) -> "SensorSpec":
        return dataclasses.replace(self, **changes)


def _take(table: dict, key: str, kind, where: str, default=dataclasses.MISSING):
    if key not in table:
        if default is dataclasses.MISSING:
            raise ValueError(f"{where}: missing key {key!r}")
        return default
    value = table[key]
    if kind is float and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if not isinstance(value, kind) or isinstance(value, bool) and kind is not bool:
        raise ValueError(f"{where}.{key} must be {kind.__name__}, got {value!r}")
    if kind is float and not math.isfinite(value):
        raise ValueError(f"{where}.{key} must be finite, got {value!r}")
    return value


def _vec3(table: dict, key: str, where: str) -> tuple[float, float, float]:
    value = table.get(key)
    if (
        not isinstance(value, list)
        or len(value) != 3
        or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
        or not all(math.isfinite(v) for v in value)
    ):
        raise ValueError(f"{where}.{key} must be a list of 3 finite numbers, got {value!r}")
    return tuple(float(v) for v in value)


def _vec2(table: dict, key: str, where: str) -> tuple[float, float]:
    value = table.get(key)
    if (
        not isinstance(value, list)
        or len(value) != 2
        or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
        or not all(math.isfinite(v) for v in value)
    ):
        raise ValueError(f"{where}.{key} must be a list of 2 finite numbers, got {value!r}")
    return (float(value[0]), float(value[1]))


def _positive(value: float, name: str) -> float:
    if not value > 0:
        raise ValueError(f"{name} must be > 0, got {value!r}")
    return value


def spec_from_dict(data: dict, source: str = "<dict>") -> SensorSpec:
    """Build and validate a :class:`SensorSpec` from a TOML-shaped dict."""
    m = data.get("membrane", {})
    shape = _take(m, "shape", str, f"{source}: membrane", "capsule")
    if shape not in ("capsule", "mesh"):
        raise ValueError(f"{source}: membrane.shape must be 'capsule' or 'mesh', got {shape!r}")
    membrane = MembraneSpec(
        shape=shape,
        radius=_positive(_take(m, "radius", float, f"{source}: membrane", 0.0115), "membrane.radius"),
        cylinder_length=_take(m, "cylinder_length", float, f"{source}: membrane", 0.044),
        base_z=_take(m, "base_z", float, f"{source}: membrane", -0.010),
        core_radius=_positive(
            _take(m, "core_radius", float, f"{source}: membrane", 0.009), "membrane.core_radius"
        ),
        mesh_edge=_positive(_take(m, "mesh_edge", float, f"{source}: membrane", 0.0005), "membrane.mesh_edge"),
        mesh_path=m.get("mesh_path"),
    )
    for name in ("radius", "cylinder_length", "core_radius", "mesh_edge"):
        value = getattr(membrane, name)
        if abs(value) > MAX_SENSOR_SIZE_M:
            raise ValueError(
                f"{source}: membrane.{name} = {value} looks like millimetres; the spec is in metres"
            )
    if membrane.cylinder_length < 0:
        raise ValueError(f"{source}: membrane.cylinder_length must be >= 0, got {membrane.cylinder_length}")
    if membrane.core_radius >= membrane.radius:
        raise ValueError(
            f"{source}: membrane.core_radius ({membrane.core_radius}) must be < radius ({membrane.radius})"
        )
    if shape == "mesh" and not membrane.mesh_path:
        raise ValueError(f"{source}: membrane.shape = 'mesh' needs membrane.mesh_path")

    c = data.get("camera", {})
    camera = CameraSpec(
        width=_take(c, "width", int, f"{source}: camera", 640),
        height=_take(c, "height", int, f"{source}: camera", 480),
        fov_y=_take(c, "fov_y", float, f"{source}: camera", math.pi / 2),
        mask_radius_px=_take(c, "mask_radius_px", float, f"{source}: camera", 240.0),
        mask_center_px=_vec2(c, "mask_center_px", f"{source}: camera") if "mask_center_px" in c else None,
    )
    if camera.width < 2 or camera.height < 2:
        raise ValueError(f"{source}: camera must be at least 2x2 px, got {camera.width}x{camera.height}")
    if not 0 < camera.fov_y < math.pi:
        raise ValueError(f"{source}: camera.fov_y must be in (0, pi) rad, got {camera.fov_y}")

    leds_data = data.get("leds")
    if not isinstance(leds_data, list) or not leds_data:
        raise ValueError(f"{source}: needs at least one [[leds]] table")
    leds = []
    for i, t in enumerate(leds_data):
        where = f"{source}: leds[{i}]"
        direction = np.asarray(_vec3(t, "direction", where))
        norm = float(np.linalg.norm(direction))
        if norm < 1e-9:
            raise ValueError(f"{where}.direction must be non-zero")
        colour = _vec3(t, "colour", where)
        if not all(0.0 <= v <= 1.0 for v in colour):
            raise ValueError(f"{where}.colour must be linear RGB in [0, 1], got {colour}")
        leds.append(
            LED(
                name=_take(t, "name", str, where, f"led{i}"),
                position=_vec3(t, "position", where),
                direction=tuple(float(v) for v in direction / norm),
                colour=colour,
                k_d=_take(t, "k_d", float, where),
                k_s=_take(t, "k_s", float, where),
                peak_nm=_take(t, "peak_nm", float, where, None),
                fwhm_nm=_take(t, "fwhm_nm", float, where, None),
            )
        )
        for key in ("peak_nm", "fwhm_nm"):
            value = getattr(leds[-1], key)
            if value is not None and not 1.0 <= value <= 2000.0:
                raise ValueError(f"{where}.{key} must be in nanometres (1-2000), got {value}")
        if max(abs(v) for v in leds[-1].position) > MAX_SENSOR_SIZE_M:
            raise ValueError(f"{where}.position {leds[-1].position} looks like millimetres; use metres")

    t = data.get("material", {})
    material = Material(
        ambient=_take(t, "ambient", float, f"{source}: material", 0.8),
        shininess=_take(t, "shininess", float, f"{source}: material", 100.0),
        clamp_specular=_take(t, "clamp_specular", bool, f"{source}: material", True),
    )
    t = data.get("elastic", {})
    elastic = Elastic(
        sigma_px=_positive(_take(t, "sigma_px", float, f"{source}: elastic", 5.0), "elastic.sigma_px"),
        radius_px=_take(t, "radius_px", int, f"{source}: elastic", 27),
        poisson_ratio=_take(t, "poisson_ratio", float, f"{source}: elastic", 0.5),
    )
    if not 0.0 <= elastic.poisson_ratio <= 0.5:
        raise ValueError(f"{source}: elastic.poisson_ratio must be in [0, 0.5], got {elastic.poisson_ratio}")
    return SensorSpec(
        name=_take(data, "name", str, source, "sensor"),
        membrane=membrane,
        camera=camera,
        leds=tuple(leds),
        material=material,
        elastic=elastic,
    )


def read_toml(path: str | Path, what: str) -> dict:
    """A TOML file's tables; FileNotFoundError or ValueError naming ``what`` and the path."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise FileNotFoundError(f"{what} {path} does not exist") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"{what} {path} is not valid TOML: {exc}") from None
    return data


def load_spec(path: str | Path | None = None) -> SensorSpec:
    """Read a sensor spec TOML file; ``None`` gives the embedded default GelTip."""
    path = Path(path) if path is not None else DEFAULT_SPEC_PATH
    data = read_toml(path, "sensor spec")
    spec = spec_from_dict(data, source=str(path))
    if spec.membrane.mesh_path and not Path(spec.membrane.mesh_path).is_absolute():
        mesh_path = str((path.parent / spec.membrane.mesh_path).resolve())
        spec = spec.replace(membrane=dataclasses.replace(spec.membrane, mesh_path=mesh_path))
    return spec


def default_spec() -> SensorSpec:
    """The embedded GelTip spec."""
    return load_spec(None)
