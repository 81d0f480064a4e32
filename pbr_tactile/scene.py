"""The GelTip as a Mitsuba 3 scene: a plain dict made by pure functions.

Inside out: the camera sits in air inside a glass tube; the tube is in optical contact
with the elastomer, a light-guiding medium (homogeneous, absorbing and scattering) bounded
by the glass core (dielectric), the painted outer surface (the coating, reflecting back
inwards) and a black base ring; the LEDs are small spherical area emitters inside the
elastomer at the base, with real spectra; the film has the webcam's spectral response.

Everything here is plain data: meshes are referenced by PLY file name, transforms as
``{"look_at": ...}`` and points as lists. ``to_mitsuba`` (in render.py) turns those into
Mitsuba objects right before the one ``mi.load_dict``; ``to_xml`` writes the same dict as
a Mitsuba XML file for other tools.
"""

from __future__ import annotations

import math
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np
import trimesh

from scenes.camera import Camera
from scenes.layout import camera_frame, tube_frame
from scenes.shapes import family
from scenes.spec import GLASS_IOR, GLASS_WALL_M, LED, SensorSpec

from .effects import Effects
from .paint import Paint
from .solid import Elastomer
from .spectra import CAMERA_BANDS_NM, gaussian, led_spectrum, mitsuba_spectrum

#: Refractive indices (dimensionless): silicone elastomer, glass core, air.
IOR_SILICONE, IOR_AIR = 1.41, 1.0
#: Radius of each LED's spherical emitter, metres.
LED_RADIUS_M = 0.35e-3
#: An LED under the glass wall's end emits from this far up inside the wall, metres.
WALL_FOOT_M = 1.0e-3
#: The direction a directional core leak (Effects.core_leak_cone_rad) emits about: up the
#: tube's wall, towards the tip.
LEAK_AXIS = (0.0, 0.0, 1.0)
#: Paths longer than this are cut. Light trapped in the membrane arrives after many
#: bounces: at 32 volpath read the tip about 30 % dark against the photon estimator, which
#: agreed once both allowed 160.
MAX_DEPTH = 160


def write_meshes(solid: Elastomer, folder: str | Path, glass_thickness: float = GLASS_WALL_M) -> dict[str, str]:
    """Write the scene's meshes as PLY files; returns {role: path}.

    Roles: ``coating`` (outer surface, normals out of the elastomer), ``core`` (elastomer
    to glass), ``base`` (elastomer's base ring), ``glass_inner`` (glass to air, normals
    into the air) and ``glass_base`` (the tube's base ring).
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    inner = solid.inner  # normals point into the glass, towards the axis
    # The tube's inner wall: the core surface moved a wall thickness further in. It keeps
    # the core's winding, so its normals point into the air inside the tube.
    glass_inner = trimesh.Trimesh(np.asarray(inner.vertices) + glass_thickness * np.asarray(inner.vertex_normals),
                                  inner.faces, process=False)
    glass_base = _ring(inner, _loop(inner), glass_inner, _loop(glass_inner), down=np.array([0.0, 0.0, -1.0]))
    meshes = {"coating": solid.outer, "core": inner, "base": solid.base, "glass_inner": glass_inner,
              "glass_base": glass_base}
    paths = {}
    for role, mesh in meshes.items():
        path = folder / f"{role}.ply"
        mesh.export(path)
        paths[role] = str(path)
    return paths


def _loop(mesh: trimesh.Trimesh) -> np.ndarray:
    loop = np.asarray(mesh.outline().entities[0].points)
    return loop[:-1] if loop[0] == loop[-1] else loop


def _ring(a: trimesh.Trimesh, la: np.ndarray, b: trimesh.Trimesh, lb: np.ndarray, down: np.ndarray) -> trimesh.Trimesh:
    n = len(la)
    V = np.vstack([a.vertices[la], b.vertices[lb]])
    i, j = np.arange(n), (np.arange(n) + 1) % n
    ring = trimesh.Trimesh(V, np.vstack([np.c_[i, j, n + j], np.c_[i, n + j, n + i]]), process=False)
    if np.dot(ring.face_normals.mean(axis=0), down) < 0:
        ring.invert()
    return ring


def _medium(effects: Effects) -> dict | None:
    if effects.sigma_t <= 0:
        return None
    return {
        "type": "homogeneous",
        "sigma_t": effects.sigma_t,
        "albedo": effects.albedo,
        "scale": 1.0,
        "phase": {"type": "isotropic"},
    }


def _coating(effects: Effects) -> dict:
    """The paint, seen from either side (``pbr_tactile.paint``)."""
    return Paint.from_effects(effects).mitsuba()


def _film(camera: Camera, effects: Effects, width: int, height: int) -> dict:
    if not effects.camera_response:
        return {"type": "hdrfilm", "width": width, "height": height, "pixel_format": "rgb",
                "rfilter": {"type": "box"}}
    film = {"type": "specfilm", "width": width, "height": height, "rfilter": {"type": "box"},
            "component_format": "float32"}
    for k, (name, (peak, fwhm)) in enumerate(CAMERA_BANDS_NM.items(), start=1):
        film[f"band{k}_{name}"] = mitsuba_spectrum(gaussian(peak, fwhm))
    return film


#: The place an LED of each entry (``scenes.spec.LED_ENTRIES``) emits from (``led_places``).
ENTRY_PLACES = {"beside": "elastomer", "edge": "wall_end", "under": "tube"}


def led_places(spec: SensorSpec) -> list[str]:
    """Where each LED emits from: by its entry (``ENTRY_PLACES``) where the spec states
    one, else by where the spec puts it: "elastomer" (at or outside the glass: moved
    radially into the middle of the elastomer wall, as the published simulation's LEDs
    ring the membrane), "tube" (in the air inside the glass tube, or under a plate, where
    it is) or "wall_end" (under the glass wall's end, below the membrane's base: its
    light enters the wall and is guided up it, so it emits from inside the wall's foot;
    a plate's rim, ``glass_edges``)."""
    core, _, _ = tube_radii(spec)
    inner = core - spec.membrane.glass_wall
    places = []
    for led, position in zip(spec.leds, tube_frame(spec, [led.position for led in spec.leds])):
        if led.entry is not None:
            places.append(ENTRY_PLACES[led.entry])
            continue
        r = math.hypot(position[0], position[1])
        places.append("elastomer" if r >= core else "tube" if r <= inner else "wall_end")
    return places


def glass_edges(spec: SensorSpec) -> tuple[np.ndarray, np.ndarray]:
    """(L, 3) where each LED's light enters the glass' end face of a body not known in
    closed form (a flat sensor's plate: its rim), and (L, 3) the face's unit inward normal
    there, camera frame: the face spans the core's base loop and the glass' underside
    under it (``pbr_tactile.scene.write_meshes``' ``glass_base``); the point is the middle
    of its span at the base-loop vertex nearest the LED's azimuth, WALL_FOOT_M inside."""
    from scenes.body import sensor_body

    body = sensor_body(spec)
    loop = body.base_loop
    normals = body.normals[loop]
    core = np.asarray(body.core.vertices)[loop]
    rotation = spec.camera.tube_to_camera()[:3, :3]  # tube to camera; its transpose back
    middle = tube_frame(spec, core - 0.5 * spec.membrane.glass_wall * normals)
    along = np.roll(middle, -1, axis=0) - np.roll(middle, 1, axis=0)  # the loop's tangent
    inward = trimesh.unitize(np.cross(normals @ rotation, along))
    inside = tube_frame(spec, np.asarray(body.membrane.vertices)).mean(axis=0)
    inward *= np.sign(np.einsum("ij,ij->i", inward, inside - middle))[:, None]  # into the body
    centre = middle.mean(axis=0)
    leds = tube_frame(spec, [led.position for led in spec.leds])
    azimuths = np.arctan2(middle[:, 1] - centre[1], middle[:, 0] - centre[0])
    nearest = [int(np.argmin(np.abs(np.angle(np.exp(1j * (azimuths - math.atan2(p[1] - centre[1],
                                                                                p[0] - centre[0])))))))
               for p in leds]
    points = middle[nearest] + WALL_FOOT_M * inward[nearest]
    return camera_frame(spec, points), inward[nearest] @ rotation.T


def tube_radii(spec: SensorSpec) -> tuple[float, float, float]:
    """The glass core's and the membrane's radius at the base, and the base's z, in the
    tube's frame, metres: a body known in closed form's (its family's ``tube``: a
    capsule's ``core_radius``, ``radius`` and ``base_z``); another shape's mean radii of its
    body's base loops (``scenes.body``)."""
    tube = family(spec.membrane.shape).tube(spec.membrane)
    if tube is not None:
        return tube.core_radius, tube.radius, tube.base_z
    from scenes.body import sensor_body

    body = sensor_body(spec)
    loop = tube_frame(spec, np.asarray(body.membrane.vertices)[body.base_loop])
    centre = loop[:, :2].mean(axis=0)
    outer = float(np.linalg.norm(loop[:, :2] - centre, axis=1).mean())
    return body.core_base_radius, outer, float(loop[:, 2].mean())


def led_centres(spec: SensorSpec) -> np.ndarray:
    """(L, 3) metres: each LED's emitter's centre (``led_places``)."""
    places = led_places(spec)
    if family(spec.membrane.shape).tube(spec.membrane) is None and "elastomer" in places:
        # In the middle of the elastomer wall under the LED: its nearest membrane point
        # moved inwards by half the thickness there (scenes.body).
        from scenes.body import sensor_body
        from scenes.proximity import closest_faces

        body = sensor_body(spec)
        at = np.array([led.position for led in spec.leds], dtype=np.float64)
        face, closest = closest_faces(body.membrane, at)
        normals = trimesh.unitize(np.asarray(body.membrane.face_normals)[face])
        middle = closest - 0.5 * body.thickness_at(closest)[:, None] * normals
        out = _led_centres_tube(spec)
        for k, place in enumerate(places):
            if place == "elastomer":
                out[k] = middle[k]
        return _at_glass_edges(spec, out)
    return _at_glass_edges(spec, _led_centres_tube(spec))


def _edge_entered(spec: SensorSpec) -> list[bool]:
    """Which LEDs enter by the glass' end face found from the body (``glass_edges``):
    those whose spec says ``entry = "edge"`` on a body not known in closed form (a tube's
    wall foot is placed in closed form, ``_led_centres_tube``)."""
    measured = family(spec.membrane.shape).tube(spec.membrane) is None
    return [measured and led.entry == "edge" for led in spec.leds]


def _at_glass_edges(spec: SensorSpec, out: np.ndarray) -> np.ndarray:
    """``out`` with each edge-entered LED (``_edge_entered``) at its glass edge."""
    entered = _edge_entered(spec)
    if any(entered):
        points, _ = glass_edges(spec)
        out[entered] = points[entered]
    return out


def _led_centres_tube(spec: SensorSpec) -> np.ndarray:
    """(L, 3) metres: each LED's emitter's centre, placed about the tube's axis
    (``led_places``; ``tube_radii``)."""
    m = spec.membrane
    core, outer, base_z = tube_radii(spec)
    pos = tube_frame(spec, [led.position for led in spec.leds])
    radial = np.linalg.norm(pos[:, :2], axis=1, keepdims=True)
    unit = np.where(radial > 0, pos[:, :2] / np.where(radial > 0, radial, 1), 0.0)
    out = pos.copy()
    for k, place in enumerate(led_places(spec)):
        if place == "elastomer":
            out[k, :2] = unit[k] * 0.5 * (core + outer)
        elif place == "wall_end":
            out[k] = [*(unit[k] * (core - 0.5 * m.glass_wall)), base_z + WALL_FOOT_M]
    return camera_frame(spec, out)


def led_beam(led: LED, place: str, glass_ior: float = GLASS_IOR,
             face_normal=None) -> tuple[tuple[float, float, float] | None, float]:
    """An LED's emitter's (cone axis, half-angle rad), where it emits from ``place``
    (``led_places``): its beam about its direction, refracted into the glass (of
    ``glass_ior``) where it enters the wall's end (Snell: a Lambertian LED's light fills
    the glass's critical cone); (None, 0) for a Lambertian emitter. ``face_normal``: the
    end face's unit inward normal (``glass_edges``), about which the beam's axis refracts
    (Snell's law for the central ray); None: the axis is the LED's direction (a tube's
    wall foot, which its LEDs face)."""
    beam = led.beam_half_angle_rad
    axis = np.asarray(led.direction, np.float64)
    if place == "wall_end":
        beam = math.asin(math.sin(beam if beam is not None else math.pi / 2) * IOR_AIR / glass_ior)
        if face_normal is not None:
            axis = _refracted(axis, np.asarray(face_normal, np.float64), IOR_AIR / glass_ior)
    return (None, 0.0) if beam is None else (tuple(map(float, axis)), float(beam))


def _refracted(d: np.ndarray, n: np.ndarray, eta: float) -> np.ndarray:
    """The unit direction ``d`` refracted into a face of unit normal ``n`` (pointing
    into the new medium) at the index ratio ``eta`` = n_1 / n_2 (< 1: no total internal
    reflection); a direction away from the face is taken as along its normal."""
    cos_i = float(np.dot(d, n))
    if cos_i <= 0:
        return n
    tangent = d - cos_i * n
    t = eta * tangent
    return trimesh.unitize(t + math.sqrt(max(0.0, 1.0 - float(np.dot(t, t)))) * n)


def led_sources(spec: SensorSpec, effects: Effects = Effects(), led_power=1.0) -> list[dict]:
    """The LEDs as spherical emitters: name, centre (m), radius (m), radiance spectrum on
    WAVELENGTHS_NM, its (peak_nm, fwhm_nm, scale) and whether it sits in the elastomer.

    With ``core_light_leak`` > 0 each LED also has a ``_leak`` emitter inside the glass,
    and at 1 only that one: an emitter of no power is left out (Mitsuba refuses a spectrum
    without mass, and it would add nothing). With ``core_leak_cone_rad`` > 0 the leak is
    directional: ``cone_axis`` (+z, up the tube) and ``cone_half_angle_rad`` say where its
    photons go (``pbr_tactile.photons.Source``); every source has both keys (None and 0
    for a Lambertian one).

    led_power : the radiance scale of every LED (the camera's exposure), or one per LED
        (``led_powers``: a unit's LEDs of another bin).
    """
    sources = []
    places = led_places(spec)
    # up the tube's axis, in the camera frame
    up = tuple(map(float, spec.camera.tube_to_camera()[:3, :3] @ np.asarray(LEAK_AXIS, np.float64)))
    entered = _edge_entered(spec)
    edges = glass_edges(spec)[1] if any(entered) else None
    for m, (led, centre, power) in enumerate(zip(spec.leds, led_centres(spec), led_powers(spec, led_power))):
        axis, half_angle = led_beam(led, places[m], spec.membrane.glass_ior, edges[m] if entered[m] else None)
        shape = led_spectrum(led.peak_nm, led.fwhm_nm, effects.led_spectra)
        peak, fwhm = (led.peak_nm, led.fwhm_nm) if effects.led_spectra else (None, None)
        leak = effects.core_light_leak
        if leak < 1:
            sources.append({"name": f"led{m}", "centre": tuple(map(float, centre)), "radius": LED_RADIUS_M,
                            "spectrum": shape * power * (1 - leak), "peak_nm": peak, "fwhm_nm": fwhm,
                            "scale": power * (1 - leak), "in_elastomer": places[m] == "elastomer",
                            "cone_axis": axis, "cone_half_angle_rad": half_angle})
        if leak > 0:
            r = tube_radii(spec)[0] - spec.membrane.glass_wall / 2
            tube = tube_frame(spec, centre)[0]
            tube[:2] *= r / max(np.linalg.norm(tube[:2]), 1e-12)
            inside = camera_frame(spec, tube)[0]
            sources.append({"name": f"led{m}_leak", "centre": tuple(map(float, inside)),
                            "radius": LED_RADIUS_M, "spectrum": shape * power * leak, "peak_nm": peak,
                            "fwhm_nm": fwhm, "scale": power * leak, "in_elastomer": False,
                            "cone_axis": up if effects.core_leak_cone_rad > 0 else None,
                            "cone_half_angle_rad": float(effects.core_leak_cone_rad)})
    return sources


def led_powers(spec: SensorSpec, led_power) -> tuple[float, ...]:
    """Each LED's radiance scale from one for all of them or one per LED; a ValueError
    naming what was expected otherwise."""
    values = tuple(led_power) if isinstance(led_power, (tuple, list, np.ndarray)) else (led_power,) * len(spec.leds)
    if len(values) != len(spec.leds) or not all(isinstance(v, (int, float, np.floating)) and math.isfinite(v)
                                                  and v > 0 for v in values):
        raise ValueError(f"led_power must be a finite radiance scale > 0, got {led_power!r}; or one per LED "
                         f"({len(spec.leds)})")
    return tuple(float(v) for v in values)


def geltip_scene(
    meshes: dict[str, str],
    spec: SensorSpec,
    camera: Camera,
    effects: Effects = Effects(),
    width: int | None = None,
    height: int | None = None,
    spp: int = 64,
    seed: int = 0,
    led_power=1.0,
) -> dict:
    """The Mitsuba scene dict of a sensor with the given meshes (see ``write_meshes``).

    width, height : film size (default: the camera's); the field of view is the camera's.
    led_power : radiance scale of every LED (the camera's exposure), or one per LED.
    """
    width = width or camera.width
    height = height or camera.height
    # Mitsuba's camera is a centred pinhole: it renders the lens' cover, which
    # pbr_tactile.render.sensor_effects reads into the lens' pixels
    cover = camera.scaled(width, height).pinhole_cover()
    fov_y = math.degrees(2 * math.atan((cover.height / 2) / cover.f))
    medium = _medium(effects)
    scene: dict = {"type": "scene"}
    if medium is not None:
        scene["elastomer"] = medium
    inside = {"interior": {"type": "ref", "id": "elastomer"}} if medium is not None else {}
    scene["integrator"] = {"type": "volpath", "max_depth": MAX_DEPTH}
    scene["sensor"] = {
        "type": "perspective",
        "fov": fov_y,
        "fov_axis": "y",
        "near_clip": 1e-4,
        "far_clip": 1.0,
        "to_world": {"look_at": {"origin": [0, 0, 0], "target": [0, 0, 1], "up": [0, -1, 0]}},
        "sampler": {"type": "independent", "sample_count": spp, "seed": seed},
        "film": _film(camera, effects, width, height),
    }
    scene["coating"] = {"type": "ply", "filename": meshes["coating"], "bsdf": _coating(effects), **inside}
    scene["core"] = {
        "type": "ply", "filename": meshes["core"],
        "bsdf": {"type": "dielectric", "int_ior": IOR_SILICONE, "ext_ior": spec.membrane.glass_ior}, **inside,
    }
    black = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}}
    scene["base"] = {"type": "ply", "filename": meshes["base"], "bsdf": black, **inside}
    scene["glass_inner"] = {
        "type": "ply", "filename": meshes["glass_inner"],
        "bsdf": {"type": "dielectric", "int_ior": spec.membrane.glass_ior, "ext_ior": IOR_AIR},
    }
    scene["glass_base"] = {"type": "ply", "filename": meshes["glass_base"], "bsdf": black}
    for k, src in enumerate(led_sources(spec, effects, led_power)):
        emitter = {
            "type": "sphere", "center": list(src["centre"]), "radius": src["radius"],
            "emitter": {"type": "area", "radiance": mitsuba_spectrum(src["spectrum"])}, "bsdf": black,
        }
        if src["in_elastomer"] and medium is not None:
            emitter["exterior"] = {"type": "ref", "id": "elastomer"}
        scene[src["name"]] = emitter
    return scene


# -- XML export -------------------------------------------------------------------------

_TAGS = {
    "volpath": "integrator", "path": "integrator", "ptracer": "integrator",
    "perspective": "sensor", "specfilm": "film", "hdrfilm": "film", "box": "rfilter", "gaussian": "rfilter",
    "independent": "sampler", "ply": "shape", "sphere": "shape", "obj": "shape",
    "diffuse": "bsdf", "dielectric": "bsdf", "twosided": "bsdf", "roughplastic": "bsdf",
    "area": "emitter", "homogeneous": "medium", "isotropic": "phase", "hg": "phase",
    "rgb": "rgb", "irregular": "spectrum",
}


def to_xml(scene: dict) -> str:
    """The scene dict as Mitsuba 3 XML (meshes stay as the PLY files it names)."""
    lines = ['<scene version="3.0.0">']
    for key, value in scene.items():
        if key != "type":
            _xml(lines, key, value, 1, top=True)
    lines.append("</scene>")
    return "\n".join(lines) + "\n"


def _xml(lines: list[str], name: str, value, depth: int, top: bool = False) -> None:
    pad = "    " * depth
    if isinstance(value, dict) and "look_at" in value:
        la = value["look_at"]
        fmt = lambda v: ", ".join(f"{float(x):g}" for x in v)  # noqa: E731
        lines.append(f'{pad}<transform name="{name}">')
        lines.append(f'{pad}    <lookat origin="{fmt(la["origin"])}" target="{fmt(la["target"])}" up="{fmt(la["up"])}"/>')
        lines.append(f"{pad}</transform>")
    elif isinstance(value, dict) and value.get("type") == "ref":
        lines.append(f'{pad}<ref name="{name}" id={quoteattr(value["id"])}/>')
    elif isinstance(value, dict) and value.get("type") == "rgb":
        lines.append(f'{pad}<rgb name="{name}" value="{", ".join(f"{float(v):g}" for v in value["value"])}"/>')
    elif isinstance(value, dict) and value.get("type") == "irregular":
        pairs = ", ".join(f"{w.strip()}:{v.strip()}" for w, v in zip(value["wavelengths"].split(","), value["values"].split(",")))
        lines.append(f'{pad}<spectrum name="{name}" value="{pairs}"/>')
    elif isinstance(value, dict):
        tag = _TAGS.get(value["type"])
        if tag is None:
            raise ValueError(f"to_xml does not know the Mitsuba plugin type {value['type']!r}")
        ident = f" id={quoteattr(name)}" if top else (f" name={quoteattr(name)}" if tag in ("bsdf",) and depth > 1 else "")
        lines.append(f'{pad}<{tag} type="{value["type"]}"{ident}>')
        for k, v in value.items():
            if k != "type":
                _xml(lines, k, v, depth + 1)
        lines.append(f"{pad}</{tag}>")
    elif isinstance(value, bool):
        lines.append(f'{pad}<boolean name="{name}" value="{str(value).lower()}"/>')
    elif isinstance(value, int):
        lines.append(f'{pad}<integer name="{name}" value="{value}"/>')
    elif isinstance(value, float):
        lines.append(f'{pad}<float name="{name}" value="{value:.9g}"/>')
    elif isinstance(value, str):
        lines.append(f"{pad}<string name={quoteattr(name)} value={quoteattr(value)}/>")
    elif isinstance(value, (list, tuple)) and len(value) == 3:
        lines.append(f'{pad}<point name="{name}" value="{", ".join(f"{float(v):.9g}" for v in value)}"/>')
    else:
        raise ValueError(f"to_xml cannot write {name} = {value!r}")
