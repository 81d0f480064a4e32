"""The sensor's body (scenes.body): one membrane and core for every consumer, checked."""

from __future__ import annotations

import dataclasses
import math
import tomllib

import numpy as np
import pytest
import trimesh

from scenes.body import sensor_body
from scenes.camera import Camera, unseen, view_angle
from scenes.geometry import membrane_mesh
from scenes.proximity import surface_distance
from scenes.shapes.mesh import check_membrane
from scenes.shapes.revolve import revolve
from scenes.spec import DEFAULT_SPEC_PATH, SensorSpec
from scenes.spec_read import default_spec, spec_from_dict

THICKNESS_M = 0.0025


@pytest.fixture(scope="module")
def capsule():
    return membrane_mesh(default_spec())


@pytest.fixture(scope="module")
def coarse():
    """A 1 mm capsule mesh and its core 2.5 mm under it: bad cores are quicker to check."""
    from scenes.shapes import capsule

    mesh = capsule.mesh(dataclasses.replace(default_spec().membrane, mesh_edge=0.001))
    core = trimesh.Trimesh(mesh.vertices - THICKNESS_M * mesh.vertex_normals, mesh.faces, process=False)
    return mesh, core


def _mesh_spec(path, **membrane) -> SensorSpec:
    data = tomllib.loads(DEFAULT_SPEC_PATH.read_text())
    data["membrane"] = {"shape": "mesh", "mesh_path": str(path), "base_z": -0.010, **membrane}
    return spec_from_dict(data, "test")


def _write(mesh: trimesh.Trimesh, folder, name="membrane.ply") -> str:
    path = folder / name
    mesh.export(path)
    return str(path)


def test_a_capsule_has_its_analytic_core_and_the_camera_sees_all_but_a_band_at_its_base(capsule):
    spec = default_spec()
    body = sensor_body(spec)
    m = spec.membrane
    assert np.all(body.thickness == m.radius - m.core_radius)
    r = np.hypot(*np.asarray(body.core.vertices)[:, :2].T)
    cylinder = np.asarray(body.core.vertices)[:, 2] < m.base_z + m.cylinder_length - 1e-4
    np.testing.assert_allclose(r[cylinder], m.core_radius, rtol=2e-3)  # vertex normals of a polygon ring
    assert body.core_base_radius == pytest.approx(m.core_radius, rel=1e-5)
    # A 90 deg pinhole 10 mm above the base sees the cylinder from 11.5 mm ahead of it.
    assert view_angle(Camera.from_spec(spec)) == pytest.approx(math.pi / 4, abs=0.01)
    out, hidden = unseen(capsule, Camera.from_spec(spec))
    assert not hidden.any()
    z = np.asarray(capsule.vertices)[:, 2]
    assert z[out].max() < m.radius + 1e-4 and z[~out].min() > m.radius - 1e-3
    assert body.seen_share == pytest.approx(0.61, abs=0.02)


def test_a_capsule_read_as_a_mesh_gets_the_same_body(coarse, tmp_path):
    """On the 1 mm capsule (the 0.5 mm one takes 7 s and agrees as closely)."""
    capsule, _ = coarse
    spec = _mesh_spec(_write(capsule, tmp_path), thickness=THICKNESS_M, mesh_edge=0.001)
    body = sensor_body(spec)
    # Derived by offsetting: the thickness is the stated one, less where the chords sag.
    assert np.abs(body.thickness - THICKNESS_M).max() < 1e-5
    parametric = default_spec()
    parametric = parametric.replace(membrane=dataclasses.replace(parametric.membrane, mesh_edge=0.001))
    reference = sensor_body(parametric)
    assert np.abs(np.asarray(body.core.vertices) - np.asarray(reference.core.vertices)).max() < 1e-5
    # And from the core mesh: the thickness is each vertex's distance to it.
    core = _write(reference.core, tmp_path, "core.ply")
    given = sensor_body(_mesh_spec(_write(capsule, tmp_path), core_mesh_path=core))
    assert np.abs(given.thickness - THICKNESS_M).max() < 1e-6


def test_millimetres_and_a_placing_transform(capsule, tmp_path):
    mm = capsule.copy()
    mm.apply_translation([0.0, 0.0, 0.02])  # the file's frame: base at z = +10 mm
    mm.apply_scale(1e3)
    path = _write(mm, tmp_path)
    place = np.eye(4)
    place[2, 3] = -0.02
    spec = _mesh_spec(path, thickness=THICKNESS_M, mesh_units="mm", mesh_transform=place.tolist())
    np.testing.assert_allclose(membrane_mesh(spec).bounds, capsule.bounds, atol=1e-9)
    with pytest.raises(ValueError, match="millimetres"):
        membrane_mesh(_mesh_spec(path, thickness=THICKNESS_M))  # a 55 m sensor
    turned = [[1, 0, 0, 0], [0, 2, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    with pytest.raises(ValueError, match="mesh_transform must be rigid"):
        _mesh_spec(path, thickness=THICKNESS_M, mesh_transform=turned)


def test_surface_distance_is_exact_against_trimesh(capsule, rng):
    points = capsule.vertices[rng.choice(len(capsule.vertices), 200)] + rng.normal(0, 2e-3, (200, 3))
    scaled = trimesh.Trimesh(capsule.vertices * 1e3, capsule.faces, process=False)
    _, expected, _ = trimesh.proximity.closest_point(scaled, points * 1e3)
    distance, closest, face = surface_distance(capsule, points)
    np.testing.assert_allclose(distance, expected * 1e-3, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(closest - points, axis=1), distance, atol=1e-12)
    on_face = trimesh.triangles.points_to_barycentric(capsule.triangles[face], closest)
    assert (on_face > -1e-6).all()  # each closest point lies on its face


# --- bad input ------------------------------------------------------------------------


def test_an_open_membrane_is_refused(capsule, tmp_path):
    holed = capsule.copy()
    tip = np.argmax(holed.triangles_center[:, 2])
    holed.update_faces(np.arange(len(holed.faces)) != tip)
    with pytest.raises(ValueError, match="holes"):
        membrane_mesh(_mesh_spec(_write(holed, tmp_path), thickness=THICKNESS_M))


def test_a_non_manifold_membrane_is_refused(capsule):
    f = np.asarray(capsule.faces)
    a, b = f[0, 0], f[0, 1]
    fin = trimesh.Trimesh(np.vstack([capsule.vertices, [[0.0, 0.0, 0.05]]]),
                          np.vstack([f, [[a, b, len(capsule.vertices)]]]), process=False)
    with pytest.raises(ValueError, match="non-manifold"):
        check_membrane(fin)


def test_a_membrane_with_inconsistent_or_inward_normals_is_refused(capsule):
    mixed = capsule.copy()
    faces = np.asarray(mixed.faces).copy()
    faces[::7] = faces[::7, ::-1]
    mixed = trimesh.Trimesh(mixed.vertices, faces, process=False)
    with pytest.raises(ValueError, match="inconsistent"):
        check_membrane(mixed)
    inward = capsule.copy()
    inward.invert()
    with pytest.raises(ValueError, match="inwards"):
        check_membrane(inward)


def test_a_core_that_crosses_the_membrane_is_refused(coarse, tmp_path):
    mesh, core = coarse
    core = core.copy()
    core.apply_scale([1.35, 1.0, 1.0])  # pokes out through the sides
    with pytest.raises(ValueError, match="crosses the membrane"):
        sensor_body(_mesh_spec(_write(mesh, tmp_path), core_mesh_path=_write(core, tmp_path, "core.ply")))


@pytest.mark.parametrize("thickness, match", [(0.0, "outside thickness_bounds"), (2e-4, "outside thickness_bounds"),
                                              (-1e-3, "outside thickness_bounds")])
def test_a_thickness_of_zero_or_below_the_minimum_is_refused(capsule, tmp_path, thickness, match):
    with pytest.raises(ValueError, match=match):
        _mesh_spec(_write(capsule, tmp_path), thickness=thickness)


def test_a_core_thinner_than_the_minimum_somewhere_is_refused(coarse, tmp_path):
    mesh, core = coarse
    V = np.asarray(core.vertices).copy()
    near = np.linalg.norm(V - [0.0, 0.0, V[:, 2].max()], axis=1) < 3e-3
    V[near, 2] += 2.2e-3  # the core rises to 0.3 mm under the apex
    core = trimesh.Trimesh(V, core.faces, process=False)
    with pytest.raises(ValueError, match="below the minimum"):
        sensor_body(_mesh_spec(_write(mesh, tmp_path), core_mesh_path=_write(core, tmp_path, "core.ply")))


def test_a_derived_thickness_is_kept_on_disk_and_a_refused_one_is_not(coarse, tmp_path, monkeypatch):
    """What a dataset's worker processes read instead of deriving it again (seconds on a
    new shape), under the membrane and the thickness; a refusal is never kept."""
    import scenes.body as body_module

    capsule, _ = coarse
    monkeypatch.setenv("TACTILE_SIM_CACHE", str(tmp_path / "cache"))
    spec = _mesh_spec(_write(capsule, tmp_path), thickness=THICKNESS_M, mesh_edge=0.001)
    first = sensor_body(spec).thickness
    assert len(list((tmp_path / "cache").glob("body-derived-*.npz"))) == 1
    body_module._bodies.clear()  # as a new process: only the disk has it
    monkeypatch.setattr(body_module, "_derived", lambda *a: pytest.fail("derived again"))
    np.testing.assert_array_equal(sensor_body(spec).thickness, first)
    # another thickness is another entry, derived afresh
    monkeypatch.undo()
    monkeypatch.setenv("TACTILE_SIM_CACHE", str(tmp_path / "cache"))
    body_module._bodies.clear()
    sensor_body(_mesh_spec(_write(capsule, tmp_path), thickness=2e-3, mesh_edge=0.001))
    assert len(list((tmp_path / "cache").glob("body-derived-*.npz"))) == 2


def test_a_derived_core_that_folds_is_refused(tmp_path, monkeypatch):
    # A 3 mm-radius groove round a capsule: a 4 mm elastomer offset inwards folds there.
    spec = default_spec()
    mesh = membrane_mesh(spec)
    V = np.asarray(mesh.vertices).copy()
    r = np.hypot(V[:, 0], V[:, 1])
    groove = 2.0e-3 * np.exp(-((V[:, 2] - 0.01) / 1.5e-3) ** 2)
    V[:, :2] *= ((r - groove) / np.maximum(r, 1e-12))[:, None]
    grooved = trimesh.Trimesh(V, mesh.faces, process=False)
    monkeypatch.setenv("TACTILE_SIM_CACHE", str(tmp_path / "cache"))
    for _ in range(2):  # refused again: a refusal is not kept
        with pytest.raises(ValueError, match="folds over|intersects itself"):
            sensor_body(_mesh_spec(_write(grooved, tmp_path), thickness=4e-3))
    assert not list((tmp_path / "cache").glob("body-*.npz"))


def test_a_membrane_the_camera_cannot_see_whole_is_refused(coarse, tmp_path):
    data = tomllib.loads(DEFAULT_SPEC_PATH.read_text())
    # A bulb wider than the base flares out of the 90 deg lens' view above the band the
    # camera cannot see at the base (8 mm: where the view meets the base's radius).
    arc = np.linspace(0.0, math.pi / 2, 40)
    z = np.linspace(-10e-3, 25e-3, 200)
    step = np.clip((z + 4e-3) / 16e-3, 0.0, 1.0)
    profile = np.vstack([np.c_[8e-3 + 6e-3 * step**2 * (3 - 2 * step), z],
                         np.c_[14e-3 * np.cos(arc), 25e-3 + 14e-3 * np.sin(arc)][1:]])
    profile[-1, 0] = 0.0
    path = _write(revolve(profile, 1e-3), tmp_path, "bulb.ply")
    data["membrane"] = {"shape": "mesh", "mesh_path": path, "base_z": -0.010, "thickness": THICKNESS_M}
    with pytest.raises(ValueError, match="out of the camera's view above the band"):
        sensor_body(spec_from_dict(data, "test"))
    capsule = coarse[0]
    path = _write(capsule, tmp_path)
    data["membrane"]["mesh_path"] = path
    # A narrow lens sees the apex alone.
    data["camera"] = {"fov_y": math.radians(30.0)}
    with pytest.raises(ValueError, match="sees .* of the membrane's area"):
        sensor_body(spec_from_dict(data, "test"))
    # A fold hides what lies behind it.
    V = np.asarray(capsule.vertices).copy()
    r = np.hypot(V[:, 0], V[:, 1])
    ridge = 6.0e-3 * np.exp(-((V[:, 2] - 0.02) / 2.0e-3) ** 2) * (V[:, 0] > 0)
    V[:, :2] *= ((r - ridge * np.clip(V[:, 0] / np.maximum(r, 1e-12), 0, 1)) / np.maximum(r, 1e-12))[:, None]
    folded = trimesh.Trimesh(V, capsule.faces, process=False)
    with pytest.raises(ValueError, match="hidden behind another part"):
        sensor_body(_mesh_spec(_write(folded, tmp_path, "folded.ply"), thickness=1e-3))


def test_spec_keys_of_one_shape_are_refused_on_another(tmp_path):
    data = tomllib.loads(DEFAULT_SPEC_PATH.read_text())
    data["membrane"] = {"shape": "mesh", "mesh_path": "x.stl", "radius": 0.01, "thickness": THICKNESS_M}
    with pytest.raises(ValueError, match="radius is for shape = 'capsule', not a 'mesh' membrane, which takes its size "
                                         "from its mesh_path"):
        spec_from_dict(data, "test")
    data["membrane"] = {"shape": "mesh", "mesh_path": "x.stl"}
    with pytest.raises(ValueError, match="needs its elastomer's thickness"):
        spec_from_dict(data, "test")
    data["membrane"] = {"shape": "capsule", "thickness": THICKNESS_M}
    with pytest.raises(ValueError, match="radius - core_radius"):
        spec_from_dict(data, "test")
    data["membrane"] = {"shape": "capsule", "core_mesh_path": "core.stl"}
    with pytest.raises(ValueError, match="core_mesh_path is for shape = 'mesh'"):
        spec_from_dict(data, "test")


def test_the_layer_model_and_the_safe_depth_read_the_body(capsule, tmp_path):
    """A thinner elastomer under a mesh membrane caps the layer's displacement and the
    protocols' depth there."""
    from scenes.elastic import MembraneLayer
    from scenes.protocol_checks import max_safe_depth_m

    spec = _mesh_spec(_write(capsule, tmp_path), thickness=1.5e-3)
    layer = MembraneLayer(capsule, spec, Camera.from_spec(spec), edge=None)
    np.testing.assert_allclose(layer.thickness, 1.5e-3, atol=5e-6)
    assert max_safe_depth_m(spec) == pytest.approx(1.5e-3, abs=5e-6)
    apex = capsule.vertices[np.argmax(capsule.vertices[:, 2])]
    assert max_safe_depth_m(spec, apex[None])[0] == pytest.approx(1.5e-3, abs=5e-6)
    assert dataclasses.replace(spec.membrane, thickness=None).elastomer_thickness is None


def test_interpolate_refuses_values_that_are_not_one_per_vertex(coarse):
    from scenes.proximity import interpolate

    mesh, _ = coarse
    with pytest.raises(ValueError, match=r"values must be \(\d+,\), one per vertex"):
        interpolate(mesh, np.zeros(len(mesh.vertices) - 1), mesh.vertices[:3])
