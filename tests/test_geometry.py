"""Membrane meshes: generated from parameters, or loaded from any file with unit checks."""

import math

import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from scenes.shapes import family
from scenes.shapes.capsule import mesh as capsule_mesh, profile as capsule_profile
from scenes.shapes.mesh import load_mesh, validate_mesh
from scenes.shapes.revolve import revolve
from scenes.spec import MembraneSpec


def test_geltip_mesh_is_a_clean_open_capsule(mesh, spec):
    m = spec.membrane
    lo, hi = mesh.bounds
    assert hi[2] == pytest.approx(family(m.shape).tube(m).apex_z, abs=1e-9)
    assert lo[2] == pytest.approx(m.base_z, abs=1e-9)
    r = np.linalg.norm(mesh.vertices[:, :2], axis=1)
    cyl = mesh.vertices[:, 2] <= m.base_z + m.cylinder_length
    assert np.allclose(r[cyl], m.radius)
    centre = np.array([0, 0, m.base_z + m.cylinder_length])
    cap = ~cyl
    assert np.allclose(np.linalg.norm(mesh.vertices[cap] - centre, axis=1), m.radius)
    assert mesh.is_winding_consistent
    assert len(mesh.outline().entities) == 1  # one open boundary: the base ring
    assert mesh.area_faces.min() > 0
    # Near-equilateral triangles everywhere (no slivers at the pole).
    assert np.degrees(trimesh.triangles.angles(mesh.triangles).min()) > 25
    # Normals point outwards.
    c = mesh.triangles_center
    axis_point = np.c_[np.zeros((len(c), 2)), np.minimum(c[:, 2], centre[2])]
    radial = c - axis_point
    assert np.all(np.einsum("ij,ij->i", mesh.face_normals, radial) > 0)
    # Area matches the analytic capsule within the discretisation error.
    area = 2 * math.pi * m.radius * m.cylinder_length + 2 * math.pi * m.radius**2
    assert mesh.area == pytest.approx(area, rel=5e-3)


@settings(max_examples=25, deadline=None)
@given(
    radius=st.floats(0.003, 0.03),
    length=st.floats(0.0, 0.06),
    edge_frac=st.floats(0.05, 0.3),
)
def test_capsules_of_any_size_are_valid_surfaces(radius, length, edge_frac):
    mesh = capsule_mesh(MembraneSpec(radius=radius, cylinder_length=length, base_z=-0.01, core_radius=radius / 2,
                                     mesh_edge=radius * edge_frac))
    assert mesh.is_winding_consistent
    assert len(mesh.outline().entities) == 1
    assert mesh.area_faces.min() > 0
    edges = mesh.edges_unique_length
    assert edges.max() < 2.5 * radius * edge_frac
    assert mesh.bounds[1, 2] == pytest.approx(-0.01 + length + radius, rel=1e-9, abs=1e-12)


@settings(max_examples=20, deadline=None)
@given(st.lists(st.tuples(st.floats(0.002, 0.02), st.floats(0.0005, 0.01)), min_size=1, max_size=5))
def test_revolve_follows_any_profile(steps):
    z = np.cumsum([0.0] + [s[1] for s in steps])
    r = [steps[0][0]] + [s[0] for s in steps]
    profile = np.c_[r, z]
    mesh = revolve(profile, 0.001)
    radial = np.linalg.norm(mesh.vertices[:, :2], axis=1)
    # Every vertex lies on the surface of revolution of the profile.
    assert np.allclose(radial, np.interp(mesh.vertices[:, 2], z, r) if np.all(np.diff(z) > 0) else radial, atol=1e-9)
    assert mesh.is_winding_consistent


def test_revolve_rejects_bad_profiles():
    with pytest.raises(ValueError, match="profile must be"):
        revolve(np.zeros((3, 3)), 0.001)
    with pytest.raises(ValueError, match="finite"):
        revolve(np.array([[0.01, 0.0], [np.nan, 0.01]]), 0.001)
    with pytest.raises(ValueError, match="edge"):
        revolve(capsule_profile(0.01, 0.02, 0.0), 0.0)


def test_load_mesh_detects_units(tmp_path, mesh):
    path = tmp_path / "membrane_mm.stl"
    mm = mesh.copy()
    mm.apply_scale(1000.0)
    mm.export(path)
    with pytest.raises(ValueError, match="looks like millimetres"):
        load_mesh(path)
    loaded = load_mesh(path, units="mm")
    assert np.allclose(loaded.bounds, mesh.bounds, atol=1e-6)
    for fmt in ("obj", "ply"):
        p = tmp_path / f"membrane.{fmt}"
        mesh.export(p)
        assert load_mesh(p).bounds == pytest.approx(mesh.bounds, abs=1e-6)


def test_malformed_meshes_are_refused(tmp_path):
    garbage = tmp_path / "garbage.stl"
    garbage.write_bytes(b"solid nothing\nthis is not an stl\n")
    with pytest.raises(ValueError, match="garbage.stl"):
        load_mesh(garbage)
    with pytest.raises(FileNotFoundError):
        load_mesh(tmp_path / "missing.stl")
    with pytest.raises(ValueError, match="units"):
        load_mesh(garbage, units="inch")
    v = np.array([[0, 0, 0], [0.01, 0, 0], [0, np.nan, 0]], float)
    with pytest.raises(ValueError, match="NaN"):
        validate_mesh(trimesh.Trimesh(v, [[0, 1, 2]], process=False))
    with pytest.raises(ValueError, match="faces"):
        validate_mesh(trimesh.Trimesh(np.eye(3) * 0.01, np.zeros((0, 3), int), process=False))


def test_nan_vertices_in_a_file_are_refused_not_dropped(tmp_path):
    path = tmp_path / "nan.obj"
    path.write_text("v 0 0 0\nv 0.01 0 0\nv 0 0.01 0\nv nan 0 0.01\nf 1 2 3\nf 1 2 4\n")
    with pytest.raises(ValueError, match="NaN"):
        load_mesh(path)
