"""The footprint test of a tap (scenes.clearance): analytic cases first (flat on flat, a
tilted approach, a concave core a point test calls safe), then the grouped search
against every vertex, then its use in the protocols."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import trimesh

from scenes.clearance import MAP_CELL_M, core_clearance, core_erosion, top_map
from scenes.indenters import make_indenter
from scenes.kinematics import indenter_to_sensor, normal_in_sensor

T_M = 2.5e-3  # the elastomer's thickness in the analytic cases
HALF_M = 2e-3  # half the side of the box indenter
N0 = np.array([0.0, -1.0, 0.0])  # normal_in_sensor(0, 0): the untilted approach


def _sheet(height, half=8e-3, step=2e-4) -> trimesh.Trimesh:
    """A core facing -y: y = T_M - height(x) over a square of side 2 * half (metres)."""
    u = np.arange(-half, half + step / 2, step)
    x, z = np.meshgrid(u, u, indexing="ij")
    vertices = np.stack([x.ravel(), (T_M - height(x)).ravel(), z.ravel()], axis=1)
    k = len(u)
    i, j = np.meshgrid(np.arange(k - 1), np.arange(k - 1), indexing="ij")
    a = (i * k + j).ravel()
    faces = np.concatenate([np.stack([a, a + 1, a + k], 1), np.stack([a + 1, a + k + 1, a + k], 1)])
    return trimesh.Trimesh(vertices, faces, process=False)


def _box_map(core, half=HALF_M):
    return {"box": top_map(trimesh.creation.box(extents=(2 * half, 2 * half, 2e-3)), core_erosion(core))}


def _clear(core, maps, depth, roll=0.0, pitch=0.0, point=(0.0, 0.0, 0.0), upto=5e-3, name="box"):
    normal = normal_in_sensor(roll, pitch)
    return float(core_clearance(core, [point], [normal], [depth], [roll], [pitch], [name], maps, upto=upto)[0])


def test_a_flat_indenter_over_a_flat_core_clears_the_thickness_less_the_depth():
    core = _sheet(lambda x: 0.0 * x)
    maps = _box_map(core)
    for depth in (0.5e-3, 2e-3, 2.5e-3, 3e-3):
        assert _clear(core, maps, depth) == pytest.approx(T_M - depth, abs=1e-12)
    # Reported up to `upto`, no further.
    assert _clear(core, maps, 0.5e-3, upto=1e-3) == 1e-3


def test_a_tilted_box_reaches_the_core_with_its_lower_edge():
    core = _sheet(lambda x: 0.0 * x)
    maps = _box_map(core)
    pitch, depth = math.radians(5.0), 2e-3
    n = normal_in_sensor(0.0, pitch)
    R = indenter_to_sensor(0.0, pitch)

    def exact(half):  # the box's top corners, moved along -n until one meets y = T_M
        tip = -depth * n
        corners = tip + np.array([[sx * half, sy * half, 0.0] for sx in (-1, 1) for sy in (-1, 1)]) @ R.T
        return float(np.min((T_M - corners[:, 1]) / np.dot(n, N0)))

    got = _clear(core, maps, depth, pitch=pitch)
    assert got < T_M - depth - 1e-4  # lower than at the contact point
    # Cautious only by the erosion (module doc): between the box and the box grown by it.
    grown = HALF_M + math.sqrt(2) * (core_erosion(core) + 2 * MAP_CELL_M)
    assert exact(grown) - 1e-12 <= got <= exact(HALF_M) + 1e-12


def test_a_concave_core_that_a_point_test_calls_safe_is_reached():
    """A flat indenter (10 mm square) 2.2 mm into a 2.5 mm layer over a core curved
    towards it (radius 20 mm): 0.3 mm clear under the contact point, but the box's edges
    reach the glass."""
    radius, depth, half = 20e-3, 2.2e-3, 5e-3
    core = _sheet(lambda x: radius - np.sqrt(radius**2 - x**2))
    maps = _box_map(core, half)

    def exact(half):
        return T_M - depth - (radius - math.sqrt(radius**2 - half**2))

    got = _clear(core, maps, depth)
    assert exact(half) < 0 < T_M - depth
    grown = half + core_erosion(core) + 2 * MAP_CELL_M
    assert exact(grown) - 1e-9 <= got <= exact(half) + 1e-9


def test_the_grouped_search_agrees_with_every_vertex(rng):
    """Random tilted taps of paper indenters around a sphere: the grouped search returns
    what the least over all of the core's vertices gives."""
    core = trimesh.creation.icosphere(subdivisions=5, radius=10e-3)
    names = ("sphere", "indented_prism", "pacman")
    maps = {name: top_map(make_indenter(name), core_erosion(core)) for name in names}
    n = 60
    roll, pitch = rng.uniform(0.0, math.pi, n), rng.uniform(0.0, math.pi / 2, n)
    normal = normal_in_sensor(roll, pitch)
    tilt = rng.normal(size=(n, 3)) * 0.05
    radial = normal + tilt
    radial /= np.linalg.norm(radial, axis=1, keepdims=True)
    point = (10e-3 + T_M) * radial
    depth = rng.uniform(1.5e-3, 3e-3, n)
    objects = rng.choice(names, n)
    upto = 4e-3
    got = core_clearance(core, point, normal, depth, roll, pitch, objects, maps, upto=upto)
    R = indenter_to_sensor(roll, pitch)
    V = np.asarray(core.vertices)
    for i in range(n):
        q = (V - (point[i] - depth[i] * normal[i])) @ R[i]
        want = min(float((q[:, 2] + maps[objects[i]].at(q[:, :2])).min()), upto)
        assert got[i] == pytest.approx(want, abs=1e-9), i
    assert (got < 0).any() and (got < upto).all()  # some reach the core; every one is measured


def test_bad_input_is_named():
    core = _sheet(lambda x: 0.0 * x)
    with pytest.raises(ValueError, match="erosion must be >= 0 metres"):
        top_map(trimesh.creation.box(extents=(1e-3, 1e-3, 1e-3)), -1.0)
    with pytest.raises(ValueError, match="cell must be > 0 metres"):
        top_map(trimesh.creation.box(extents=(1e-3, 1e-3, 1e-3)), 0.0, cell=0.0)
    with pytest.raises(ValueError, match=r"objects \['cone'\] have no top map"):
        _clear(core, _box_map(core), 1e-3, name="cone")


# --- The protocols --------------------------------------------------------------------


@pytest.fixture(scope="module")
def paw():
    from pathlib import Path

    from scenes.geometry import membrane_mesh
    from scenes.spec_read import load_spec

    spec = load_spec(Path(__file__).resolve().parents[1] / "scenes" / "sensors" / "paw.toml")
    return spec, membrane_mesh(spec)


def test_the_protocols_press_no_tap_into_the_glass(paw):
    """On the paw's waist the indented prism's nominal taps would reach the core at 2 mm:
    the base protocol presses them only until they touch it, and validate refuses them
    at 2 mm, though that is within the 2.5 mm under their contact points."""
    from scenes.protocol import base_protocol
    from scenes.protocol_checks import core_safe_depth_m, max_safe_depth_m, validate
    from scenes.taps import Protocol

    spec, mesh = paw
    protocol = base_protocol(spec, mesh, ("indented_prism", "sphere"))
    depth = np.array([t.depth for t in protocol.taps])
    safe = core_safe_depth_m(spec, mesh, protocol.taps)
    assert (depth <= safe + 1e-9).all()
    capped = np.flatnonzero(depth < 2e-3 - 1e-9)
    assert len(capped) and all(protocol.taps[i].object == "indented_prism" for i in capped)
    tap = protocol.taps[capped[0]]
    deeper = dataclasses.replace(tap, depth=2e-3)
    assert deeper.depth < max_safe_depth_m(spec, [tap.point], mesh)[0]
    with pytest.raises(ValueError, match=rf"base tap {tap.index} .*indented_prism indenter would reach .* mm into "
                                         "the glass core under its footprint"):
        validate(Protocol("base", (deeper,), None), spec, mesh)


def test_a_tap_of_an_unknown_object_is_refused(paw):
    from scenes.protocol import base_protocol
    from scenes.protocol_checks import validate
    from scenes.taps import Protocol

    spec, mesh = paw
    tap = dataclasses.replace(base_protocol(spec, mesh, ("sphere",)).taps[0], object="feather")
    with pytest.raises(ValueError, match="object 'feather' is none of the indenters"):
        validate(Protocol("custom", (tap,), None), spec, mesh)
