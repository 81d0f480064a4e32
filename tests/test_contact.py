"""Analytic contacts: known shapes pressed to known depths give known depth maps."""

import numpy as np
import pytest
import trimesh

from scenes.contact import pose_indenter, press, sphere_depth, surface_point
from scenes.shapes import family


def test_sphere_on_the_tip_reaches_the_commanded_depth(mesh, camera, ref, spec):
    depth = press(ref, camera, mesh, trimesh.primitives.Sphere(radius=0.004), (camera.cx, camera.cy), 0.0015)
    # The pixel nearest the axis sees the sphere's lowest point, tip_z - 1.5 mm.
    assert depth[239:241, 319:321].min() == pytest.approx(family(spec.membrane.shape).tube(spec.membrane).apex_z - 0.0015, abs=2e-5)
    contact = depth < ref
    assert contact.any() and not contact[~camera.mask].any()
    assert np.all(depth <= ref)


@pytest.mark.parametrize("pixel", [(420.0, 300.0), (150.0, 200.0), (330.0, 30.0)])
def test_indentation_along_the_normal_equals_the_commanded_depth(mesh, camera, ref, pixel):
    point, normal = surface_point(mesh, camera, pixel)
    depth = press(ref, camera, mesh, trimesh.primitives.Sphere(radius=0.003), pixel, 0.001)
    hit = ref > depth
    P = depth[hit, None] * camera.rays[hit]
    # The deepest imprint, measured along the normal, is the commanded 1 mm.
    assert (np.dot(point - P, normal)).max() == pytest.approx(0.001, abs=3e-5)


def test_exact_sphere_and_mesh_sphere_agree(camera):
    centre = np.array([0.002, -0.001, 0.03])
    exact = sphere_depth(centre, 0.004, camera)
    ico = trimesh.creation.icosphere(subdivisions=5, radius=0.004)
    ico.apply_translation(centre)
    from scenes.contact import indenter_depth

    meshed = indenter_depth(ico, camera)
    both = np.isfinite(exact) & np.isfinite(meshed)
    assert both.sum() > 1000
    err = np.abs(exact[both] - meshed[both])
    # Facets of the icosphere: tiny in the bulk, larger only at grazing rays.
    assert np.median(err) < 5e-6 and np.percentile(err, 99) < 3e-5


def test_any_mesh_indenter_presses_to_depth(mesh, camera, ref):
    box = trimesh.creation.box((0.004, 0.004, 0.004))
    pixel = (380.0, 260.0)
    point, normal = surface_point(mesh, camera, pixel)
    posed = pose_indenter(box, point, normal, 0.0012, spin=0.4)
    assert (posed.vertices @ normal).min() == pytest.approx(point @ normal - 0.0012)
    depth = press(ref, camera, mesh, box, pixel, 0.0012, spin=0.4)
    assert (depth < ref).sum() > 100


def test_bad_contacts_are_refused(mesh, camera, ref):
    sphere = trimesh.primitives.Sphere(radius=0.003)
    with pytest.raises(ValueError, match="depth must be in"):
        press(ref, camera, mesh, sphere, (320, 240), 0.05)
    with pytest.raises(ValueError, match="depth must be in"):
        press(ref, camera, mesh, sphere, (320, 240), -0.001)
    with pytest.raises(ValueError, match="pixel must lie"):
        press(ref, camera, mesh, sphere, (700, 240), 0.001)
    with pytest.raises(ValueError, match="ref_depth"):
        press(ref[:10], camera, mesh, sphere, (320, 240), 0.001)
    with pytest.raises(ValueError, match="shape must be a trimesh"):
        press(ref, camera, mesh, "sphere", (320, 240), 0.001)
    with pytest.raises(ValueError, match="unit vector"):
        pose_indenter(sphere, np.zeros(3), np.array([0, 0, 2.0]), 0.001)


from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402


@settings(max_examples=30, deadline=None)
@given(
    x=st.floats(-0.01, 0.01), y=st.floats(-0.01, 0.01), z=st.floats(0.01, 0.05), radius=st.floats(0.001, 0.008)
)
def test_sphere_hits_lie_on_the_sphere_and_face_the_camera(small_camera, x, y, z, radius):
    centre = np.array([x, y, z])
    depth = sphere_depth(centre, radius, small_camera)
    hit = np.isfinite(depth)
    P = depth[hit, None] * small_camera.rays[hit]
    assert np.allclose(np.linalg.norm(P - centre, axis=1), radius, atol=1e-9)
    # The nearer of the two roots: the surface there faces the camera.
    assert np.all(np.einsum("ij,ij->i", P - centre, P) <= 1e-12)
