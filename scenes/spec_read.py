"""Sensor specs read: TOML files (a file may name a base file, ``base = "geltip.toml"``,
relative to it, and state only what differs: its tables override the base's key by key,
``read_sensor_file``) and their dicts, each table checked, into ``scenes.spec``'s
dataclasses. Each membrane is checked through its shape family (``scenes.shapes``), each
camera's lens through ``scenes.camera``; both sit below this module.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from pathlib import Path

import numpy as np

from .camera import PROJECTIONS, Camera, lens_table, project
from .shapes import TABLE_KEYS, family
from .spec import (
    BASE_KEY, CameraSpec, DEFAULT_SHAPE, DEFAULT_SPEC_PATH, DISTORTION_BOUND, Elastic,
    FOV_Y_BOUNDS, GLASS_IOR, GLASS_IOR_BOUNDS, GLASS_WALL_M, Housing, LED, LEDGroup, LED_ENTRIES,
    MAX_SENSOR_SIZE_M, Material, MembraneSpec, NAMED_ARRAYS, SENSORS_DIR, SensorSpec,
    THICKNESS_BOUNDS_M, TILT_BOUND_RAD,
)


def _take(table: dict, key: str, kind, where: str, default=dataclasses.MISSING):
    if key not in table or table[key] is None and default is None:  # None: an optional key left unset
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


def _vector(table: dict, key: str, where: str, n: int) -> tuple[float, ...]:
    """``table[key]`` as a tuple of ``n`` finite numbers; ValueError naming it otherwise."""
    value = table.get(key)
    if (
        not isinstance(value, list)
        or len(value) != n
        or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
        or not all(math.isfinite(v) for v in value)
    ):
        raise ValueError(f"{where}.{key} must be a list of {n} finite numbers, got {value!r}")
    return tuple(float(v) for v in value)


def _positive(value: float, name: str) -> float:
    if not value > 0:
        raise ValueError(f"{name} must be > 0, got {value!r}")
    return value


def spec_from_dict(data: dict, source: str = "<dict>") -> SensorSpec:
    """Build and validate a :class:`SensorSpec` from a TOML-shaped dict (a whole sensor:
    one that names a base file is read with :func:`read_sensor_file`)."""
    if BASE_KEY in data:
        raise ValueError(f"{source}: base = {data[BASE_KEY]!r} names a base file, resolved relative to the file that "
                         "names it: read the file with load_spec (or read_sensor_file)")
    membrane = _membrane(data.get("membrane", {}), f"{source}: membrane")

    camera = _camera(data.get("camera", {}), f"{source}: camera", membrane)
    housing = _housing(data.get("housing", {}), f"{source}: housing")

    leds_data = data.get("leds", [])
    groups_data = data.get("led_groups", [])
    if not isinstance(leds_data, list) or not isinstance(groups_data, list):
        raise ValueError(f"{source}: leds and led_groups must be arrays of tables ([[leds]], [[led_groups]])")
    if not leds_data and not groups_data:
        raise ValueError(f"{source}: needs at least one [[leds]] or [[led_groups]] table")
    leds = []
    group_names = [t.get("name") for t in groups_data if isinstance(t, dict)]
    for i, t in enumerate(leds_data):
        where = f"{source}: leds[{i}]"
        if t.get("group") is not None:
            # a group's own LED, as a spec written out whole (dataclasses.asdict) lists it:
            # the group lays it out again
            if t["group"] not in group_names:
                raise ValueError(f"{where}.group {t['group']!r} names no [[led_groups]] table")
            continue
        direction = np.asarray(_vector(t, "direction", where, 3))
        norm = float(np.linalg.norm(direction))
        if norm < 1e-9:
            raise ValueError(f"{where}.direction must be non-zero")
        leds.append(LED(name=_take(t, "name", str, where, f"led{i}"), position=_vector(t, "position", where, 3),
                        direction=tuple(float(v) for v in direction / norm), **_optics(t, where)))
        if max(abs(v) for v in leds[-1].position) > MAX_SENSOR_SIZE_M:
            raise ValueError(f"{where}.position {leds[-1].position} looks like millimetres; use metres")
        _outside_glass(math.hypot(*leds[-1].position[:2]), leds[-1].position[2], membrane, f"{where}.position")
    groups = tuple(_led_group(t, f"{source}: led_groups[{i}]", membrane) for i, t in enumerate(groups_data))
    for group in groups:
        leds.extend(group.leds())
    for led in leds:
        check_in_housing(led.position, housing, f"{source}: LED {led.name!r}")
    names = [led.name for led in leds] + [group.name for group in groups]
    repeated = sorted({n for n in names if names.count(n) > 1})
    if repeated:
        raise ValueError(f"{source}: LED and LED group names must be unique, repeated: {', '.join(repeated)}")

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
        led_groups=groups,
        housing=housing,
    )


def _housing(t, where: str) -> Housing:
    """A [housing] table, checked: each bound a finite length in metres."""
    if not isinstance(t, dict):
        raise ValueError(f"{where} must be a table ([housing])")
    unknown = sorted(set(t) - {"radius", "floor_z"})
    if unknown:
        raise ValueError(f"{where}: unknown keys {', '.join(unknown)} (expected radius, floor_z)")
    radius = _take(t, "radius", float, where, None)
    floor_z = _take(t, "floor_z", float, where, None)
    for name, value in (("radius", radius), ("floor_z", floor_z)):
        if value is not None and not (math.isfinite(value) and abs(value) <= MAX_SENSOR_SIZE_M):
            raise ValueError(f"{where}.{name} must be a finite length in metres, got {value}")
    if radius is not None and radius <= 0:
        raise ValueError(f"{where}.radius must be > 0 m, got {radius}")
    return Housing(radius=radius, floor_z=floor_z)


def check_in_housing(position, housing: Housing, where: str) -> None:
    """Refuse a point (camera frame, m) outside the housing: further than its radius from
    the camera's axis, or nearer the camera than its floor; ValueError naming ``where``
    and the bound."""
    radius = math.hypot(float(position[0]), float(position[1]))
    if housing.radius is not None and radius > housing.radius * (1 + 1e-9):
        raise ValueError(f"{where}: {radius * 1e3:.2f} mm from the axis is outside the housing, whose radius is "
                         f"{housing.radius * 1e3:.2f} mm ([housing] radius)")
    if housing.floor_z is not None and float(position[2]) < housing.floor_z - 1e-12:
        raise ValueError(f"{where}: z = {float(position[2]) * 1e3:.2f} mm is below the housing's floor at z = "
                         f"{housing.floor_z * 1e3:.2f} mm ([housing] floor_z)")


def _membrane(m: dict, where: str) -> MembraneSpec:
    """The [membrane] table, checked: its shape, and its family's keys, parameters and rules
    (``scenes.shapes``); the core's thickness and its bounds; the glass."""
    if not isinstance(m, dict):
        raise ValueError(f"{where} must be a table, got {m!r}")
    shape = family(_take(m, "shape", str, where, DEFAULT_SHAPE), f"{where}.shape")
    foreign = [(owner, key) for key, owner in TABLE_KEYS.items() if owner != shape.NAME and m.get(key) is not None]
    if foreign:  # keys that another family alone takes
        owner = foreign[0][0]
        keys = [key for o, key in foreign if o == owner]
        raise ValueError(f"{where}: {', '.join(keys)} {'is' if len(keys) == 1 else 'are'} for shape = {owner!r}, not a "
                         f"{shape.NAME!r} membrane, which takes its size from {shape.SIZE_FROM} and its core from "
                         f"{shape.CORE_FROM}")
    lo_hi = m.get("thickness_bounds", list(THICKNESS_BOUNDS_M))
    table = {"thickness_bounds": list(lo_hi) if isinstance(lo_hi, tuple) else lo_hi}
    bounds = _vector(table, "thickness_bounds", where, 2)
    if not 0 < bounds[0] < bounds[1] <= MAX_SENSOR_SIZE_M:
        raise ValueError(f"{where}.thickness_bounds must be [min, max] metres with 0 < min < max, got {list(bounds)}")
    transform = m.get("mesh_transform")
    if transform is not None:
        transform = _rigid(transform, f"{where}.mesh_transform")
    params = m.get("params", {})
    if isinstance(params, (list, tuple)) and all(isinstance(p, (list, tuple)) and len(p) == 2 for p in params):
        params = dict(params)  # as a spec written out whole (dataclasses.asdict) lists them
    if not isinstance(params, dict):
        raise ValueError(f"{where}.params must be a table of numbers ([membrane.params]), got {params!r}")
    params = shape.membrane_params(params, f"{where}.params")
    membrane = MembraneSpec(
        shape=shape.NAME,
        radius=_positive(_take(m, "radius", float, where, 0.0115), "membrane.radius"),
        cylinder_length=_take(m, "cylinder_length", float, where, 0.044),
        base_z=_take(m, "base_z", float, where, -0.010),
        core_radius=_positive(_take(m, "core_radius", float, where, 0.009), "membrane.core_radius"),
        mesh_edge=_positive(_take(m, "mesh_edge", float, where, 0.0005), "membrane.mesh_edge"),
        mesh_path=_take(m, "mesh_path", str, where, None),
        glass_wall=_positive(_take(m, "glass_wall", float, where, GLASS_WALL_M), "membrane.glass_wall"),
        glass_ior=_take(m, "glass_ior", float, where, GLASS_IOR),
        params=tuple(sorted((str(k), float(v)) for k, v in params.items())),
        thickness=_take(m, "thickness", float, where, None),
        core_mesh_path=_take(m, "core_mesh_path", str, where, None),
        mesh_units=_take(m, "mesh_units", str, where, "m"),
        mesh_transform=transform,
        thickness_bounds=bounds,
    )
    for name in ("radius", "cylinder_length", "core_radius", "mesh_edge", "glass_wall"):
        value = getattr(membrane, name)
        if abs(value) > MAX_SENSOR_SIZE_M:
            raise ValueError(f"{where}.{name} = {value} looks like millimetres; the spec is in metres")
    if membrane.cylinder_length < 0:
        raise ValueError(f"{where}.cylinder_length must be >= 0, got {membrane.cylinder_length}")
    if membrane.core_radius >= membrane.radius:
        raise ValueError(f"{where}.core_radius ({membrane.core_radius}) must be < radius ({membrane.radius})")
    if membrane.glass_wall >= membrane.core_radius:
        raise ValueError(f"{where}.glass_wall ({membrane.glass_wall} m) must be thinner than the tube's "
                         f"outer radius core_radius ({membrane.core_radius} m)")
    if not GLASS_IOR_BOUNDS[0] <= membrane.glass_ior <= GLASS_IOR_BOUNDS[1]:
        raise ValueError(f"{where}.glass_ior must be a glass' refractive index in "
                         f"[{GLASS_IOR_BOUNDS[0]}, {GLASS_IOR_BOUNDS[1]}], got {membrane.glass_ior}")
    if membrane.mesh_units not in ("m", "mm"):
        raise ValueError(f"{where}.mesh_units must be 'm' or 'mm', got {membrane.mesh_units!r}")
    shape.check(membrane, where)
    tube = shape.tube(membrane)
    thickness, what = ((tube.thickness, "radius - core_radius") if tube is not None
                       else (membrane.thickness, "thickness"))
    if thickness is not None and not bounds[0] <= thickness <= bounds[1]:
        raise ValueError(f"{where}: the elastomer's thickness ({what}) is {thickness * 1e3:.3g} mm, outside "
                         f"thickness_bounds [{bounds[0] * 1e3:.3g}, {bounds[1] * 1e3:.3g}] mm")
    return membrane


def _rigid(value, where: str) -> tuple[float, ...]:
    """A 4x4 rigid transform given as 4 rows of 4 numbers, checked: a rotation (orthonormal,
    determinant +1), a translation in metres, last row 0 0 0 1. Returns its 16 numbers."""
    try:
        matrix = np.array(value, dtype=np.float64)
    except (TypeError, ValueError):
        matrix = None
    if matrix is not None and matrix.shape == (16,):  # as a spec written out whole lists it
        matrix = matrix.reshape(4, 4)
    if matrix is None or matrix.shape != (4, 4) or not np.isfinite(matrix).all():
        raise ValueError(f"{where} must be 4 rows of 4 finite numbers (a row-major 4x4 transform), got {value!r}")
    rotation = matrix[:3, :3]
    if not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-6) or np.linalg.det(rotation) < 0:
        raise ValueError(f"{where} must be rigid: its upper-left 3x3 must be a rotation (orthonormal, det +1); "
                         "scale a mesh with mesh_units")
    if not np.allclose(matrix[3], [0, 0, 0, 1]):
        raise ValueError(f"{where}'s last row must be [0, 0, 0, 1], got {matrix[3].tolist()}")
    if np.abs(matrix[:3, 3]).max() > MAX_SENSOR_SIZE_M:
        raise ValueError(f"{where}'s translation {matrix[:3, 3].tolist()} looks like millimetres; use metres")
    return tuple(float(v) for v in matrix.ravel())


def _camera(c: dict, where: str, membrane: MembraneSpec) -> CameraSpec:
    """The [camera] table, checked: its size, field of view, lens, principal point and
    image circle, and that the lens sees the tube."""
    camera = CameraSpec(
        width=_take(c, "width", int, where, 640),
        height=_take(c, "height", int, where, 480),
        fov_y=_take(c, "fov_y", float, where, math.pi / 2),
        mask_radius_px=_take(c, "mask_radius_px", float, where, 240.0),
        mask_center_px=_vector(c, "mask_center_px", where, 2) if c.get("mask_center_px") is not None else None,
        principal_point_px=(_vector(c, "principal_point_px", where, 2) if c.get("principal_point_px") is not None
                            else None),
        distortion=_vector(c, "distortion", where, 2) if c.get("distortion") is not None else (0.0, 0.0),
        projection=_take(c, "projection", str, where, "pinhole"),
        offset_m=_vector(c, "offset_m", where, 2) if c.get("offset_m") is not None else (0.0, 0.0),
        tilt_rad=_vector(c, "tilt_rad", where, 2) if c.get("tilt_rad") is not None else (0.0, 0.0),
    )
    if camera.width < 2 or camera.height < 2:
        raise ValueError(f"{where} must be at least 2x2 px, got {camera.width}x{camera.height}")
    lo, hi = FOV_Y_BOUNDS
    if not lo <= camera.fov_y <= hi:
        raise ValueError(f"{where}.fov_y must be in [{lo:.4f}, {hi:.4f}] rad (10 to 170 deg), got {camera.fov_y}")
    if camera.projection not in PROJECTIONS:
        raise ValueError(f"{where}.projection must be one of {PROJECTIONS}, got {camera.projection!r}")
    if max(map(abs, camera.distortion)) > DISTORTION_BOUND:
        raise ValueError(f"{where}.distortion (k1, k2) must each lie in [-{DISTORTION_BOUND}, {DISTORTION_BOUND}], "
                         f"got {list(camera.distortion)}")
    shape = family(membrane.shape)
    tube = shape.tube(membrane)
    bore = tube.core_radius - membrane.glass_wall if tube is not None else math.inf  # else scenes.body
    if math.hypot(*camera.offset_m) >= bore:
        raise ValueError(f"{where}.offset_m {list(camera.offset_m)} puts the camera {math.hypot(*camera.offset_m):.4g} m "
                         f"off the tube's axis, outside its bore (radius {bore:.4g} m; metres, not millimetres?)")
    if max(map(abs, camera.tilt_rad)) > TILT_BOUND_RAD:
        raise ValueError(f"{where}.tilt_rad {list(camera.tilt_rad)} must each lie in [-{TILT_BOUND_RAD:.4f}, "
                         f"{TILT_BOUND_RAD:.4f}] rad (15 deg)")
    if not shape.SEATED and (any(camera.offset_m) or any(camera.tilt_rad)):
        raise ValueError(f"{where}.offset_m and tilt_rad seat a generated membrane; a membrane.mesh_path mesh is "
                         "already in the camera frame, or placed there by membrane.mesh_transform")
    if camera.mask_radius_px <= 0:
        raise ValueError(f"{where}.mask_radius_px must be > 0 px, got {camera.mask_radius_px}")
    _, theta = lens_table(*camera.distortion, camera.projection, 1.0)
    if theta[-1] < camera.fov_y / 2:
        raise ValueError(f"{where}.distortion {list(camera.distortion)} folds the {camera.projection} lens back at "
                         f"{math.degrees(theta[-1]):.1f} deg from the axis, inside its field of view "
                         f"({math.degrees(camera.fov_y) / 2:.1f} deg each side): no lens images that")
    for key, value in (("principal_point_px", camera.principal_point_px), ("mask_center_px", camera.mask_center_px)):
        if value is not None and not (0 <= value[0] <= camera.width - 1 and 0 <= value[1] <= camera.height - 1):
            raise ValueError(f"{where}.{key} {list(value)} must lie in the {camera.width}x{camera.height} frame")
    lens = Camera.from_spec(camera)
    if not np.isfinite(lens.slopes()[0][lens.mask]).all():
        raise ValueError(f"{where}: the lens (distortion {list(camera.distortion)}) folds inside the image circle: "
                         "part of the circle would see no ray")
    if tube is not None:
        u, v = project((camera.tube_to_camera() @ [0.0, 0.0, tube.apex_z, 1.0])[:3], lens)
        if not lens.mask[min(max(int(round(v)), 0), lens.height - 1), min(max(int(round(u)), 0), lens.width - 1)] \
                or not (0 <= u <= lens.width - 1 and 0 <= v <= lens.height - 1):
            raise ValueError(f"{where}: the camera puts the tube's tip at pixel ({u:.1f}, {v:.1f}), outside its image "
                             f"circle (radius {camera.mask_radius_px} px): check the principal point and image circle")
    return camera


def _optics(t: dict, where: str) -> dict:
    """An LED's (or an LED group's) colour, Phong constants and emission spectrum."""
    colour = _vector(t, "colour", where, 3)
    if not all(0.0 <= v <= 1.0 for v in colour):
        raise ValueError(f"{where}.colour must be linear RGB in [0, 1], got {colour}")
    out = {"colour": colour, "k_d": _take(t, "k_d", float, where), "k_s": _take(t, "k_s", float, where),
           "peak_nm": _take(t, "peak_nm", float, where, None), "fwhm_nm": _take(t, "fwhm_nm", float, where, None),
           "beam_half_angle_rad": _take(t, "beam_half_angle_rad", float, where, None),
           "entry": _take(t, "entry", str, where, None)}
    if out["entry"] is not None and out["entry"] not in LED_ENTRIES:
        raise ValueError(f"{where}.entry must be one of {', '.join(LED_ENTRIES)} (where its light enters), got "
                         f"{out['entry']!r}")
    for key in ("peak_nm", "fwhm_nm"):
        if out[key] is not None and not 1.0 <= out[key] <= 2000.0:
            raise ValueError(f"{where}.{key} must be in nanometres (1-2000), got {out[key]}")
    beam = out["beam_half_angle_rad"]
    if beam is not None and not 0.0 < beam <= math.pi / 2:
        raise ValueError(f"{where}.beam_half_angle_rad must be in (0, pi/2] rad, got {beam}")
    return out


def _outside_glass(radius: float, height: float, membrane: MembraneSpec, where: str) -> None:
    """Refuse an LED inside the glass wall (``radius`` from the axis and ``height`` z, m) of
    a body known in closed form (its family's ``tube``); other bodies' glass is checked
    with their core (``scenes.body``)."""
    tube = family(membrane.shape).tube(membrane)
    if tube is None:
        return
    inner = tube.core_radius - membrane.glass_wall
    if inner < radius < tube.core_radius and height >= tube.base_z:
        raise ValueError(f"{where}: {radius * 1e3:.2f} mm from the axis puts the LED inside the glass wall "
                         f"({inner * 1e3:.2f} to {tube.core_radius * 1e3:.2f} mm from the axis, above the "
                         f"membrane's base at z = {tube.base_z * 1e3:.1f} mm): place it in the tube, under the "
                         "wall (below the base) or outside it")


def _led_group(t: dict, where: str, membrane: MembraneSpec) -> LEDGroup:
    """An [[led_groups]] table, checked: at least one LED, a span in [0, 2 pi], a ring
    that does not cut the glass wall."""
    count = _take(t, "count", int, where)
    if count < 1:
        raise ValueError(f"{where}.count must be at least 1 LED, got {count}")
    span = _take(t, "arc_span_rad", float, where)
    if not 0.0 <= span <= 2 * math.pi + 1e-12:
        raise ValueError(f"{where}.arc_span_rad must be in [0, 2 pi] rad (at most the whole ring, 360 deg), got "
                         f"{span} ({math.degrees(span):.1f} deg)")
    radius = _positive(_take(t, "ring_radius", float, where), f"{where}.ring_radius")
    height = _take(t, "height", float, where)
    if max(radius, abs(height)) > MAX_SENSOR_SIZE_M:
        raise ValueError(f"{where}: ring_radius {radius} and height {height} look like millimetres; use metres")
    _outside_glass(radius, height, membrane, f"{where}.ring_radius")
    tilt = _take(t, "tilt_rad", float, where, 0.0)
    if not abs(tilt) < math.pi / 2:
        raise ValueError(f"{where}.tilt_rad must be within (-pi/2, pi/2) of the axis, got {tilt}")
    return LEDGroup(name=_take(t, "name", str, where), count=count,
                    arc_centre_rad=_take(t, "arc_centre_rad", float, where), arc_span_rad=min(span, 2 * math.pi),
                    ring_radius=radius, height=height, tilt_rad=tilt, **_optics(t, where))


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


def _merged_tables(base: dict, over: dict) -> dict:
    """``base`` with ``over``'s keys: tables within both merged key by key, any other value
    of ``over`` in place of the base's."""
    out = dict(base)
    for key, value in over.items():
        old = out.get(key)
        out[key] = _merged_tables(old, value) if isinstance(value, dict) and isinstance(old, dict) else value
    return out


def _merged_entries(base: list, over: list) -> list:
    """An array of tables over its base's: each entry merged into the base's entry of the
    same ``name``, entries of new names (or none) added after the base's."""
    out = list(base)
    index = {e["name"]: i for i, e in enumerate(out) if isinstance(e, dict) and "name" in e}
    for entry in over:
        name = entry.get("name") if isinstance(entry, dict) else None
        if name in index:
            out[index[name]] = _merged_tables(out[index[name]], entry)
        else:
            out.append(entry)
    return out


def _merged_sensor(base: dict, over: dict) -> dict:
    """A sensor file's tables over its base's (:func:`read_sensor_file`)."""
    base = dict(base)
    m, m_base = over.get("membrane"), base.get("membrane")
    if isinstance(m, dict) and isinstance(m_base, dict):
        shape = m_base.get("shape", DEFAULT_SHAPE)
        if m.get("shape", shape) != shape:  # another shape: drop what sizes the base's
            base["membrane"] = {k: v for k, v in m_base.items() if k != "params" and TABLE_KEYS.get(k) != shape}
    out = _merged_tables(base, {k: v for k, v in over.items() if k not in NAMED_ARRAYS})
    for key in NAMED_ARRAYS:
        if key in over:
            value, old = over[key], base.get(key)
            merge = isinstance(value, list) and value and isinstance(old, list)
            out[key] = _merged_entries(old, value) if merge else value
    out.pop(BASE_KEY, None)
    return out


def read_sensor_file(path: str | Path) -> dict:
    """A sensor file's tables over those of the base it names, and so on down its chain.

    A file's ``base = "other.toml"`` (relative to the file) names the file it overrides:

    - a table (``[camera]``, ``[membrane]``, ``[membrane.params]``, ...) merges key by
      key: the file's keys replace the base's, the base's others stay;
    - ``[[leds]]`` and ``[[led_groups]]`` (NAMED_ARRAYS) merge entry by entry: an entry
      merges into the base's entry of the same ``name``, an entry of a new name is added
      after the base's; an empty array (``leds = []``) drops the base's;
    - any other value (a number, a string, an array) replaces the base's;
    - a membrane of another ``shape`` than its base's keeps none of what sizes the base's
      shape: that family's own keys (``scenes.shapes.TABLE_KEYS``) and its
      ``[membrane.params]``.

    A base's relative mesh paths are its own: they resolve relative to the base.

    Raises FileNotFoundError naming the file whose base is missing, and ValueError for a
    base that is not a file name or a chain that comes back to one of its files.
    """
    path = Path(path)
    files = [path]
    layers = [read_toml(path, "sensor spec")]
    while BASE_KEY in layers[-1]:
        named_by, base = files[-1], layers[-1][BASE_KEY]
        if not isinstance(base, str) or not base:
            raise ValueError(f"sensor spec {named_by}: base must name a sensor file (relative to this one), "
                             f"got {base!r}")
        base_path = named_by.parent / base
        if base_path.resolve() in {f.resolve() for f in files}:
            raise ValueError(f"sensor spec {named_by}: base {base!r} makes a cycle: "
                             + " -> ".join(str(f) for f in files + [base_path]))
        data = read_toml(base_path, f"sensor spec {named_by}: its base")
        m = data.get("membrane")
        for key in ("mesh_path", "core_mesh_path"):
            value = m.get(key) if isinstance(m, dict) else None
            if isinstance(value, str) and value and not Path(value).is_absolute():
                m[key] = str((base_path.parent / value).resolve())
        files.append(base_path)
        layers.append(data)
    out = layers.pop()
    while layers:
        out = _merged_sensor(out, layers.pop())
    return out


def spec_file(name_or_path: str | Path, base: str | Path | None = None) -> Path:
    """A sensor spec's TOML: a file's path (relative to ``base`` where given), or a shipped
    sensor's name (``digit``, ``gelsight_mini``, ``gelsight``, ...: ``scenes/sensors/<name>.toml``)
    where no such file exists."""
    text = str(name_or_path)
    path = Path(text)
    if base is not None and not path.is_absolute():
        path = (Path(base) / path).resolve()
    if path.is_file() or "/" in text or text.endswith(".toml"):
        return path
    shipped = SENSORS_DIR / f"{text}.toml"
    return shipped if shipped.is_file() else path


def load_spec(path: str | Path | None = None) -> SensorSpec:
    """Read a sensor spec TOML file (over its base, :func:`read_sensor_file`), by its path or
    a shipped sensor's name (:func:`spec_file`); or a dataset's folder, whose
    ``dataset.json`` records its sensor (an imported capture's: the spec at the frames'
    size and pixel, the unit's own); ``None`` gives the default GelTip."""
    path = spec_file(path) if path is not None else DEFAULT_SPEC_PATH
    if path.is_dir():
        import json

        meta = path / "dataset.json"
        try:
            sensor = json.loads(meta.read_text())["sensor"]
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise ValueError(f"spec {path}: a folder must be a dataset whose dataset.json records its sensor "
                             f"({exc.__class__.__name__}: {exc})") from None
        return spec_from_dict(sensor, source=str(meta))
    data = read_sensor_file(path)
    spec = spec_from_dict(data, source=str(path))
    for key in ("mesh_path", "core_mesh_path"):
        value = getattr(spec.membrane, key)
        if value and not Path(value).is_absolute():
            spec = spec.replace(membrane=dataclasses.replace(spec.membrane, **{key: str((path.parent / value).resolve())}))
    return spec


def default_spec() -> SensorSpec:
    """The default GelTip spec (DEFAULT_SPEC_PATH)."""
    return load_spec(None)


def with_led_groups(spec: SensorSpec, groups) -> SensorSpec:
    """``spec`` with its LED groups replaced, each checked as a spec file's would be, and
    its single LEDs kept."""
    checked = tuple(_led_group({k: list(v) if isinstance(v, tuple) else v
                                for k, v in dataclasses.asdict(g).items() if v is not None},
                               f"{spec.name}: led_groups[{i}]", spec.membrane) for i, g in enumerate(groups))
    singles = tuple(led for led in spec.leds if led.group is None)
    return spec.replace(leds=singles + tuple(led for g in checked for led in g.leds()), led_groups=checked)
