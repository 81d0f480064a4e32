"""Principal curvatures of a membrane and its classes of region (scenes.curvature),
against surfaces whose curvatures are known in closed form."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from scenes import curvature
from scenes.geometry import membrane_mesh
from scenes.spec_read import load_spec

R = 0.01  # m


def _inverted(mesh: trimesh.Trimesh) -> trimesh.Trimesh:
    return trimesh.Trimesh(mesh.vertices, mesh.faces[:, ::-1], process=False)


def _tube(radius: float) -> trimesh.Trimesh:
    """An open cylinder 40 mm long, edges about 0.7 mm, normals outward."""
    profile = np.stack([np.full(67, radius), np.linspace(-0.02, 0.02, 67)], axis=1)
    return trimesh.creation.revolve(profile, sections=105)


def test_a_sphere_is_convex_with_curvature_one_over_its_radius_and_concave_seen_from_inside():
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=R)
    points = sphere.vertices[::500]
    k = curvature.principal_curvatures(sphere, points)
    np.testing.assert_allclose(k, 1 / R, rtol=0.01)
    assert set(curvature.classify(k)) == {"convex"}
    k_in = curvature.principal_curvatures(_inverted(sphere), points)
    np.testing.assert_allclose(k_in, -1 / R, rtol=0.01)
    assert set(curvature.classify(k_in)) == {"concave"}


def _grid_faces(n: int) -> np.ndarray:
    i = np.arange(n - 1)
    a = (i[:, None] * n + i[None, :]).ravel()
    return np.concatenate([np.stack([a, a + 1, a + n + 1], 1), np.stack([a, a + n + 1, a + n], 1)])


def test_a_cylinder_is_cylindrical_a_trough_from_inside_and_a_plane_flat():
    cyl = _tube(R)
    side = np.array([[R * np.cos(a), R * np.sin(a), z] for a in (0.3, 2.0, 4.0) for z in (-0.01, 0.0, 0.01)])
    k = curvature.principal_curvatures(cyl, side)
    np.testing.assert_allclose(k[:, 0], 0.0, atol=1.0)  # 1/m
    np.testing.assert_allclose(k[:, 1], 1 / R, rtol=0.01)
    assert set(curvature.classify(k)) == {"cylindrical"}
    assert set(curvature.classify(curvature.principal_curvatures(_inverted(cyl), side))) == {"trough"}
    u, v = np.meshgrid(np.linspace(-0.02, 0.02, 61), np.linspace(-0.02, 0.02, 61))
    grid = np.stack([u.ravel(), v.ravel(), np.zeros(u.size)], axis=1)
    plane = trimesh.Trimesh(grid, _grid_faces(61))
    k = curvature.principal_curvatures(plane, np.array([[0.0, 0.0, 0.0], [0.01, -0.008, 0.0]]))
    np.testing.assert_allclose(k, 0.0, atol=1e-6)  # 1/m
    assert set(curvature.classify(k)) == {"flat"}


def test_the_inside_of_a_torus_is_a_saddle_with_its_known_curvatures():
    major, minor = 0.02, 0.008
    torus = trimesh.creation.torus(major, minor, major_sections=256, minor_sections=128)
    k = curvature.principal_curvatures(torus, np.array([[major - minor, 0, 0], [major + minor, 0, 0]]))
    # Across the tube 1/minor; along it cos(phi) / (major + minor cos(phi)).
    np.testing.assert_allclose(k[0], [-1 / (major - minor), 1 / minor], rtol=0.02)
    np.testing.assert_allclose(k[1], [1 / (major + minor), 1 / minor], rtol=0.02)
    assert list(curvature.classify(k)) == ["saddle", "convex"]


def test_the_geltip_is_a_cylinder_and_a_hemisphere_and_the_paw_alone_has_saddles():
    geltip = load_spec(None)
    mesh = membrane_mesh(geltip)
    v = np.asarray(mesh.vertices)
    radius = geltip.membrane.radius
    body = v[(v[:, 2] > v[:, 2].min() + 0.004) & (v[:, 2] < v[:, 2].max() - radius - 0.003)][::200]
    k = curvature.principal_curvatures(mesh, body)
    np.testing.assert_allclose(k[:, 1], 1 / radius, rtol=0.01)
    np.testing.assert_allclose(k[:, 0], 0.0, atol=1.0)
    assert set(curvature.classify(k)) == {"cylindrical"}
    tip = v[v[:, 2] > v[:, 2].max() - radius + 0.003][::50]
    np.testing.assert_allclose(curvature.principal_curvatures(mesh, tip), 1 / radius, rtol=0.02)
    from pathlib import Path

    sensors = Path(__file__).parents[1] / "scenes" / "sensors"
    for name, saddles in (("thumb", False), ("paw", True)):
        m = membrane_mesh(load_spec(sensors / f"{name}.toml"))
        classes = curvature.classify(curvature.principal_curvatures(m, np.asarray(m.vertices)[::20]))
        assert ("saddle" in set(classes)) is saddles, (name, np.unique(classes, return_counts=True))


def test_classes_follow_the_signs_beyond_the_flat_tolerance_and_bad_input_is_refused():
    tol = 1 / curvature.FLAT_RADIUS_M
    k = np.array([[2, 3], [0, 3], [0, 0], [-3, 3], [-3, 0], [-3, -2], [0.9, 1.5]]) * tol
    assert list(curvature.classify(k)) == ["convex", "cylindrical", "flat", "saddle", "trough", "concave",
                                           "cylindrical"]
    assert list(curvature.classify(k[:, ::-1])) == list(curvature.classify(k))  # order of the pair is free
    assert set(curvature.classify(k)) <= set(curvature.CLASSES)
    sphere = trimesh.creation.icosphere(radius=R)
    with pytest.raises(ValueError, match="points must be a finite"):
        curvature.principal_curvatures(sphere, np.array([[0.0, 0.0, np.nan]]))
    with pytest.raises(ValueError, match="points must be a finite"):
        curvature.principal_curvatures(sphere, np.zeros((3, 2)))
    with pytest.raises(ValueError, match="radius must be a positive"):
        curvature.principal_curvatures(sphere, sphere.vertices[:1], radius=0.0)
    with pytest.raises(ValueError, match="at least two of the mesh's mean edges"):
        curvature.vertex_curvatures(trimesh.creation.icosphere(subdivisions=1, radius=R))
    with pytest.raises(ValueError, match="k must be a finite"):
        curvature.classify(np.zeros((3, 3)))
    with pytest.raises(ValueError, match="flat_radius must be a positive"):
        curvature.classify(np.zeros((3, 2)), flat_radius=-1.0)
