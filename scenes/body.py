"""The sensor's body: its membrane, the glass core under it and the elastomer between.

Every consumer reads the one body of a spec (:func:`sensor_body`): the elastic layer
model (thickness under each point), the protocols' safe depth, the MuJoCo rig's glass
and the reference's elastomer solid and glass. The body is the outer membrane surface
(``scenes.geometry.membrane_mesh``) and the elastomer's thickness under each of its
vertices, measured along the vertex's inward normal; the core's surface is the membrane
moved inwards by it (:attr:`SensorBody.core`), vertex for vertex.

- A body known in closed form (its family's ``tube``: the capsule's) is
  ``radius - core_radius`` thick everywhere, exactly (a hemisphere and a cylinder offset
  inwards are a hemisphere and a cylinder).
- A shape family or a mesh with a stated ``thickness`` derives its core by that offset,
  checked: no face of the core turns over (a fold, where the membrane is convex with a
  radius under the thickness), the core does not cross itself, and no part of the
  membrane comes nearer the core than the thickness (a thin neck): the thickness under a
  vertex is the lesser of the stated one and that distance, and it must stay within the
  spec's ``thickness_bounds``.
- A mesh with its own core (``core_mesh_path``) measures the thickness under each vertex
  as its distance to that core, checked: the core lies inside the membrane, does not
  cross it, and the thickness stays within bounds (a core that does not reach under a
  part of the membrane leaves it too thick there).

Every body is checked against its camera as well: the camera must see the membrane whole
(``scenes.camera.unseen``), except a band at the base that it cannot see because it sits
inside the tube there; a part hidden anywhere else (behind a bend, outside the image
circle) is refused. A family whose gel fills the view (a flat sensor's pad) must instead
put gel in every pixel (:func:`check_covers`).
"""

from __future__ import annotations

import dataclasses
import math
from collections import OrderedDict
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import trimesh

from .camera import Camera, cast_rays, unseen, view_angle
from .geometry import crossing_faces, membrane_mesh, mesh_digest
from .proximity import interpolate, surface_distance
from .shapes import family
from .shapes.mesh import base_loop, load_mesh, validate_mesh
from .spec import SensorSpec

#: A face of the derived core whose normal turns this far from the membrane's has folded.
MAX_CORE_TURN_RAD = math.radians(60.0)
#: The least share of the membrane's area the camera must see (the GelTip's published
#: camera, a 90 deg pinhole 10 mm above the base, sees 61 %). Not for a pad: a flat
#: sensor's gel reaches past the view, to the LEDs at its edge, and its camera must see
#: gel in every pixel instead (:func:`check_covers`).
MIN_SEEN_SHARE = 0.5
#: Pixels across the frame at which :func:`check_covers` casts its rays.
COVER_CHECK_WIDTH = 64
#: Bodies :func:`sensor_body` keeps, the most recently used.
KEPT_BODIES = 4
#: Version of the thickness kept on disk: bump it when _derived or _given change.
BODY_CACHE_VERSION = 1


@dataclass(frozen=True, eq=False)
class SensorBody:
    """A membrane and the elastomer's thickness under it.

    membrane : the outer surface, camera frame, metres, open at its base, normals out.
    thickness : (V,) float64, metres, the elastomer's thickness under each vertex, along
        its inward (vertex) normal.
    seen_share : share of the membrane's area the camera sees.
    """

    membrane: trimesh.Trimesh
    thickness: np.ndarray
    seen_share: float = 1.0

    @cached_property
    def normals(self) -> np.ndarray:
        """(V, 3) unit outward vertex normals of the membrane."""
        return np.asarray(self.membrane.vertex_normals, dtype=np.float64)

    @cached_property
    def core(self) -> trimesh.Trimesh:
        """The glass core's outer surface: each membrane vertex moved inwards by the
        thickness under it; the membrane's faces, normals pointing out of the core."""
        V = np.asarray(self.membrane.vertices) - self.thickness[:, None] * self.normals
        return trimesh.Trimesh(V, np.asarray(self.membrane.faces), process=False)

    @property
    def min_thickness(self) -> float:
        """The thinnest the elastomer is anywhere, metres."""
        return float(self.thickness.min())

    @cached_property
    def base_loop(self) -> np.ndarray:
        """(K,) int, the membrane's base vertices, in order."""
        return base_loop(self.membrane)

    @property
    def core_base_radius(self) -> float:
        """Mean distance of the core's base loop from its centre, metres: the glass tube's
        outer radius at the base (a capsule's ``core_radius``)."""
        loop = np.asarray(self.core.vertices)[self.base_loop]
        return float(np.linalg.norm(loop[:, :2] - loop[:, :2].mean(axis=0), axis=1).mean())

    def thickness_at(self, points: np.ndarray) -> np.ndarray:
        """(N,) the thickness under points (N, 3) on or near the membrane, metres:
        interpolated on the nearest point of the membrane."""
        return interpolate(self.membrane, self.thickness, points)


def _derived(membrane: trimesh.Trimesh, thickness: float, name: str) -> np.ndarray:
    """The thickness under each vertex of a core offset inwards by ``thickness``, checked."""
    normals = np.asarray(membrane.vertex_normals)
    core = trimesh.Trimesh(np.asarray(membrane.vertices) - thickness * normals, membrane.faces, process=False)
    turn = np.einsum("ij,ij->i", core.face_normals, membrane.face_normals)
    folded = turn < math.cos(MAX_CORE_TURN_RAD)
    if folded.any():
        where = np.asarray(membrane.triangles_center)[folded].mean(axis=0) * 1e3
        raise ValueError(f"{name}: its core, offset {thickness * 1e3:.3g} mm inwards, folds over at {int(folded.sum())} "
                         f"faces (about {where.round(1).tolist()} mm): the membrane curves there more tightly than the "
                         "elastomer is thick (a convex radius under the thickness); give a thinner elastomer or a core "
                         "mesh (core_mesh_path)")
    crossed = crossing_faces(core)
    if len(crossed):
        where = np.asarray(core.triangles_center)[crossed].mean(axis=0) * 1e3
        raise ValueError(f"{name}: its core, offset {thickness * 1e3:.3g} mm inwards, intersects itself at "
                         f"{len(crossed)} faces (about {where.round(1).tolist()} mm)")
    return np.minimum(thickness, surface_distance(membrane, core.vertices)[0])


def _given(membrane: trimesh.Trimesh, core: trimesh.Trimesh, name: str) -> np.ndarray:
    """The thickness under each vertex, its distance to a given core, checked: the core
    does not cross the membrane and lies inside it (a core that does not reach under a
    part of the membrane leaves it too thick there: ``thickness_bounds``)."""
    both = trimesh.util.concatenate([membrane, core])
    crossed = crossing_faces(both)
    crossed = crossed[crossed < len(membrane.faces)]
    if len(crossed):
        where = np.asarray(membrane.triangles_center)[crossed].mean(axis=0) * 1e3
        raise ValueError(f"{name}: the core crosses the membrane at {len(crossed)} of its faces (about "
                         f"{where.round(1).tolist()} mm): the core must lie wholly under it")
    V, n = np.asarray(membrane.vertices), np.asarray(membrane.vertex_normals)
    thickness, closest, _ = surface_distance(core, V)
    outside = np.einsum("ij,ij->i", closest - V, n) > 0
    if outside.any():
        raise ValueError(f"{name}: the core lies outside the membrane at {int(outside.sum())} of its {len(V)} "
                         "vertices: it must lie wholly under it, in the membrane's units and frame")
    return thickness


def _check_thickness(thickness: np.ndarray, bounds: tuple[float, float], membrane: trimesh.Trimesh, name: str) -> None:
    lo, hi = bounds
    for bad, what, worst in ((thickness < lo, "below the minimum", np.argmin), (thickness > hi, "above the maximum",
                                                                                np.argmax)):
        if bad.any():
            k = int(worst(thickness))
            raise ValueError(f"{name}: the elastomer is {thickness[k] * 1e3:.3g} mm thick at "
                             f"{(np.asarray(membrane.vertices)[k] * 1e3).round(1).tolist()} mm ({int(bad.sum())} vertices "
                             f"{what}), outside thickness_bounds [{lo * 1e3:.3g}, {hi * 1e3:.3g}] mm")


def check_seen(membrane: trimesh.Trimesh, camera: Camera, name: str = "membrane",
               min_share: float = MIN_SEEN_SHARE) -> float:
    """Refuse a membrane the camera cannot see whole; return the share of its area seen.

    The camera sits inside the tube, so it cannot see a band above the base: the part
    of the membrane outside the widest cone it sees whole (``view_angle``) below the
    height where that cone meets the base's widest radius. Refused, naming where:

    - any part hidden behind another part of the membrane (a bend, a fold);
    - any part out of view above that band (outside the image circle, past the lens'
      field of view);
    - a camera that sees less than ``min_share`` of the membrane's area.
    """
    out, hidden = unseen(membrane, camera)
    V = np.asarray(membrane.vertices)
    loop = V[base_loop(membrane)]
    edge = float(np.sqrt(np.asarray(membrane.area_faces).mean() * 4 / math.sqrt(3)))
    band = float(np.hypot(loop[:, 0], loop[:, 1]).max()) / math.tan(view_angle(camera)) + edge
    for bad, why in ((hidden, "hidden behind another part of it"),
                     (out & (V[:, 2] > band), f"out of the camera's view above the band it cannot see at the base "
                                              f"(z up to {band * 1e3:.1f} mm)")):
        if bad.any():
            raise ValueError(f"{name}: the camera cannot see it whole: {int(bad.sum())} vertices (from "
                             f"{(V[bad].min(axis=0) * 1e3).round(1).tolist()} to "
                             f"{(V[bad].max(axis=0) * 1e3).round(1).tolist()} mm, camera frame) are {why}; widen the "
                             "lens (camera.fov_y, camera.projection), move the camera or change the shape")
    area = np.asarray(membrane.area_faces)
    seen = ~(out | hidden)[np.asarray(membrane.faces)].any(axis=1)
    share = float(area[seen].sum() / area.sum())
    if share < min_share:
        raise ValueError(f"{name}: the camera sees {share:.0%} of the membrane's area, under {min_share:.0%}: "
                         "widen the lens (camera.fov_y, camera.projection) or lower the camera")
    return share


def check_covers(membrane: trimesh.Trimesh, camera: Camera, name: str = "membrane") -> None:
    """Refuse a membrane that leaves a pixel of the image circle without gel: every ray of
    the camera (scaled to COVER_CHECK_WIDTH pixels across) must meet it. A pad's check in
    place of MIN_SEEN_SHARE (a flat sensor's frame sees gel everywhere)."""
    small = camera.scaled(COVER_CHECK_WIDTH, max(1, round(COVER_CHECK_WIDTH * camera.height / camera.width)))
    hit = cast_rays(membrane, small)
    missed = int(small.mask.sum()) - len(hit.pixels)
    if missed > 0:
        raise ValueError(f"{name}: {missed} of {int(small.mask.sum())} rays of the camera (at {small.width}x"
                         f"{small.height}) miss the membrane: the image would show no gel there; widen the pad "
                         "(membrane.params.radius) or narrow the lens (camera.fov_y)")


def _check_leds(spec: SensorSpec, body: SensorBody, name: str) -> None:
    """Refuse an LED inside the glass wall under a measured body (one known in closed form,
    a ``Tube``, has its LEDs checked with its spec): between the core's base radius and a
    wall's thickness less, above the base."""
    outer = body.core_base_radius
    inner = outer - spec.membrane.glass_wall
    base_z = float(np.asarray(body.membrane.vertices)[body.base_loop, 2].mean())
    centre = np.asarray(body.core.vertices)[body.base_loop, :2].mean(axis=0)
    for led in spec.leds:
        r = float(np.linalg.norm(np.asarray(led.position[:2]) - centre))
        if inner < r < outer and led.position[2] >= base_z:
            raise ValueError(f"{name}: LED {led.name!r} sits {r * 1e3:.2f} mm from the tube's axis, inside the glass "
                             f"wall ({inner * 1e3:.2f} to {outer * 1e3:.2f} mm) above the membrane's base")


_bodies: OrderedDict = OrderedDict()


def _kept_thickness(kind: str, key: list, build) -> np.ndarray:
    """The thickness ``build()`` derives and checks (seconds on a new shape's mesh: every
    worker process of a dataset needs it), kept on disk (``scenes.cache``) under what it
    depends on; a mesh that fails the checks raises and is never kept."""
    from .cache import cached, make_key

    return cached(f"body-{kind}", make_key(BODY_CACHE_VERSION, *key), lambda: {"thickness": build()})["thickness"]


def sensor_body(spec: SensorSpec, membrane: trimesh.Trimesh | None = None) -> SensorBody:
    """The body of a sensor spec, built and checked (module doc); kept across calls,
    keyed by the membrane and everything of the spec it reads.

    membrane : the spec's membrane mesh when the caller has it (``membrane_mesh(spec)``).
    Raises ValueError naming what is wrong.
    """
    from .cache import make_key

    membrane = membrane_mesh(spec) if membrane is None else membrane
    m = spec.membrane
    key = make_key(mesh_digest(membrane), dataclasses.asdict(m), dataclasses.asdict(spec.camera),
                   [led.position for led in spec.leds])
    if key in _bodies:
        _bodies.move_to_end(key)
        return _bodies[key]
    name = f"sensor {spec.name!r}"
    camera = Camera.from_spec(spec)
    shape = family(m.shape)
    tube = shape.tube(m)
    if tube is not None:
        thickness = np.full(len(membrane.vertices), tube.thickness)
    elif m.core_mesh_path is not None:
        core = load_mesh(m.core_mesh_path, units=m.mesh_units)
        if m.mesh_transform is not None:
            core.apply_transform(np.reshape(m.mesh_transform, (4, 4)))
        validate_mesh(core, f"{name}: core {m.core_mesh_path}")
        thickness = _kept_thickness("given", [mesh_digest(membrane), mesh_digest(core)],
                                    lambda: _given(membrane, core, name))
    else:
        thickness = _kept_thickness("derived", [mesh_digest(membrane), m.thickness, MAX_CORE_TURN_RAD],
                                    lambda: _derived(membrane, m.thickness, name))
    _check_thickness(thickness, m.thickness_bounds, membrane, name)
    fills = shape.FILLS_VIEW
    body = SensorBody(membrane, thickness, check_seen(membrane, camera, name, 0.0 if fills else MIN_SEEN_SHARE))
    if fills:
        check_covers(membrane, camera, name)
    if tube is None:
        _check_leds(spec, body, name)
    _bodies[key] = body
    while len(_bodies) > KEPT_BODIES:
        _bodies.popitem(last=False)
    return body


def checked_membrane(spec: SensorSpec) -> trimesh.Trimesh:
    """The spec's membrane mesh (``membrane_mesh``), once its body has passed
    :func:`sensor_body`'s checks: what a command that loads a spec builds on."""
    mesh = membrane_mesh(spec)
    sensor_body(spec, mesh)
    return mesh
