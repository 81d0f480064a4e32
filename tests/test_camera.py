"""Camera model: projection, back-projection and the no-contact depth D_ref."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from scenes.camera import back_project, check_depth, project, reference_depth, undistorted_radius
from scenes.shapes import family

#: The issue's bound on D_ref against the published sim_depth/bkg.npy, metres RMS.
DREF_RMS_BOUND_M = 0.1e-3


def test_published_intrinsics(camera):
    assert camera.f == pytest.approx(240.0)
    assert (camera.cx, camera.cy) == (319.5, 239.5)
    assert camera.mask.sum() == pytest.approx(np.pi * 240**2, rel=0.01)


@settings(max_examples=50, deadline=None)
@given(u=st.floats(0, 639), v=st.floats(0, 479), z=st.floats(0.001, 0.1))
def test_back_projection_inverts_projection(camera, u, v, z):
    p = np.array([(u - camera.cx) * z / camera.f, (v - camera.cy) * z / camera.f, z])
    assert project(p, camera) == pytest.approx([u, v], abs=1e-9)


def test_back_project_a_flat_wall(camera):
    depth = np.full(camera.shape, 0.02)
    P = back_project(depth, camera)
    assert np.allclose(P[..., 2], 0.02)
    assert project(P, camera)[200, 300] == pytest.approx([300, 200])


def test_reference_depth_is_analytic_on_the_capsule(mesh, camera, spec):
    depth, valid = reference_depth(mesh, camera)
    assert valid[camera.mask].all()
    # On the axis the camera sees the tip apex; at the circle's edge (45 deg) the cylinder.
    assert depth[239:241, 319:321].max() == pytest.approx(family(spec.membrane.shape).tube(spec.membrane).apex_z, abs=2e-5)
    edge = depth[240, 320 + 239]
    assert edge == pytest.approx(spec.membrane.radius * camera.f / 239.5, rel=2e-3)


def test_reference_depth_matches_the_published_map(mesh, camera, reference_dir):
    published = np.load(reference_dir / "sim_depth" / "bkg.npy")
    depth, _ = reference_depth(mesh, camera)
    err = (depth - published)[camera.mask]
    rms = float(np.sqrt(np.mean(err.astype(np.float64) ** 2)))
    print(f"D_ref vs published bkg.npy: RMS {rms * 1e3:.4f} mm, max {np.abs(err).max() * 1e3:.4f} mm")
    assert rms < DREF_RMS_BOUND_M


@pytest.mark.parametrize(
    "bad, message",
    [
        (np.zeros((480, 640, 3)), r"must be \(480, 640\) float"),
        (np.zeros((240, 320)), r"must be \(480, 640\) float"),
        (np.ones((480, 640), np.uint16), r"must be \(480, 640\) float"),
        (np.full((480, 640), np.nan), "NaN"),
        (-np.ones((480, 640)), "> 0"),
        (np.full((480, 640), 30.0), "plausible"),
        ([[1.0]], "numpy array"),
    ],
)
def test_bad_depth_maps_are_refused(camera, bad, message):
    with pytest.raises(ValueError, match=message):
        check_depth(bad, camera)


def test_scaled_camera_keeps_the_field_of_view(camera):
    small = camera.scaled(160, 120)
    assert small.f == pytest.approx(60.0)
    assert small.mask_radius_px == pytest.approx(60.0)
    assert small.rays[0, 0] == pytest.approx(camera.rays[0, 0], rel=0.02)


def test_image_circle_matches_the_real_capture(camera, reference_dir):
    from scenes.images import read_rgb

    real = read_rgb(reference_dir / "real" / "bkg.png", camera.shape)
    assert np.array_equal(real.sum(axis=-1) > 0, camera.mask)


def test_block_mean_averages_whole_blocks_over_the_image_axes():
    from scenes.images import block_mean

    image = np.arange(4 * 6, dtype=np.float32).reshape(4, 6)
    out = block_mean(np.stack([image, image + 1])[..., None], 2, (1, 2))
    assert out.shape == (2, 2, 3, 1) and out.dtype == np.float32
    # the top-left block of 0, 1, 6, 7
    assert out[0, 0, 0, 0] == 3.5 and out[1, 0, 0, 0] == 4.5
    np.testing.assert_allclose(block_mean(image[..., None], 2)[..., 0], out[0, ..., 0])
    assert block_mean(image, 1) is image
    with pytest.raises(ValueError, match="6x4 pixels cannot be averaged in blocks of 4x4"):
        block_mean(image, 4)


@settings(max_examples=50, deadline=None)
@given(st.floats(-0.3, 0.6), st.floats(-0.05, 0.1))
def test_undistorted_radius_inverts_the_lens_polynomial(k1, k2):
    r_d = np.linspace(0.0, 1.7, 200)
    r_u = undistorted_radius(r_d, k1, k2)
    reached = np.isfinite(r_u)
    assert reached[0] and reached[:50].all()  # the centre of the image circle is always seen
    assert np.allclose(r_u[reached] * (1 + k1 * r_u[reached] ** 2 + k2 * r_u[reached] ** 4), r_d[reached], atol=1e-5)
    assert (np.diff(r_u[reached]) > 0).all()  # one branch, rising from 0


def test_a_strong_barrel_reaches_no_further_than_its_fold():
    # r_d = r_u (1 - 0.4 r_u^2) is largest at r_u = 1 / sqrt(1.2): r_d = 0.6086
    fold = (1 / 1.2**0.5) * (1 - 0.4 / 1.2)
    r_u = undistorted_radius(np.array([0.5, fold - 1e-3, fold + 1e-3, 1.0]), -0.4, 0.0)
    assert np.isfinite(r_u[:2]).all() and np.isnan(r_u[2:]).all()
    assert r_u[0] > 0.5  # a barrel draws points in: each pixel looks further out
    assert undistorted_radius(np.array([0.7]), 0.2, 0.0)[0] < 0.7  # a pincushion pushes them out
    assert np.array_equal(undistorted_radius(np.array([0.3, 1.2]), 0.0, 0.0), [0.3, 1.2])
