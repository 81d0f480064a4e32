"""The fast path: the chain's parts analytically, and the windowed renderer against it."""

import numpy as np
import pytest
import trimesh

from phong_reference.background import make_background
from phong_reference.bake import bake
from scenes.elastic import deform
from phong_reference.normals import normals
from phong_reference.phong import shade
from phong_reference.render import Renderer, light_vectors, render
from scenes.camera import back_project
from scenes.contact import press
from scenes.images import read_rgb, write_rgb
from scenes.spec import LED, Elastic, Material


@pytest.fixture(scope="module")
def linear(mesh, camera, spec, tmp_path_factory):
    return bake(mesh, camera, spec.leds, "linear", use_cache=False)


def test_elastic_smoothing_keeps_no_contact_and_spreads_a_dent(camera):
    ref = np.full(camera.shape, 0.03)
    assert np.array_equal(deform(ref, ref, Elastic()), ref)
    d = ref.copy()
    d[240, 320] = 0.029  # a 1 mm spike
    out = deform(d, ref, Elastic())
    assert out[240, 320] == d[240, 320]  # min keeps the indenter itself
    assert out[240, 330] < 0.03  # the spread reaches neighbours
    assert out[240, 320 + 28] == 0.03  # but not beyond the 55x55 kernel
    # The spread conserves the displaced volume (Gaussian has unit mass).
    assert (ref - deform(d, ref, Elastic(sigma_px=2.0, radius_px=12))).sum() >= 0.001 - 1e-12


def test_normals_of_a_plane_and_a_sphere(camera):
    P = back_project(np.full(camera.shape, 0.02, np.float32), camera, channels_first=True)
    assert P.shape == (3, 480, 640)
    N, valid = normals(P)
    assert valid.all()
    assert np.allclose(N[:, 5:-5, 5:-5], np.array([0, 0, -1.0])[:, None, None], atol=1e-6)
    # A sphere about the camera: normals point back at the centre.
    rays = camera.rays / np.linalg.norm(camera.rays, axis=-1, keepdims=True)
    P = np.ascontiguousarray((0.03 * rays).transpose(2, 0, 1))
    N, _ = normals(P)
    assert np.allclose(N[:, 5:-5, 5:-5], -P[:, 5:-5, 5:-5] / 0.03, atol=1e-3)


def test_normals_match_scipy_sobel(rng):
    from scipy import ndimage

    P = rng.random((3, 40, 50))
    N, _ = normals(P)
    du = np.stack([ndimage.sobel(P[c], axis=1) for c in range(3)])
    dv = np.stack([ndimage.sobel(P[c], axis=0) for c in range(3)])
    n = np.cross(du, dv, axis=0)
    n /= np.linalg.norm(n, axis=0)
    n *= -np.sign((n * P).sum(axis=0))
    assert np.allclose(N, n, atol=1e-9)


def test_phong_matches_the_equation_by_hand():
    P = np.array([[0.0], [0.0], [0.02]])
    N = np.array([[0.0], [0.0], [-1.0]])
    L_m = np.array([0.6, 0.0, -0.8])
    led = LED("l", (0, 0, 0), (0, 0, 1), (1.0, 0.5, 0.25), k_d=0.9, k_s=0.3)
    mat = Material(ambient=0.5, shininess=3.0)
    I = shade(P, N, L_m[None, :, None], [led], mat, np.full((3, 1), 0.2))
    d = 0.8
    R = 2 * d * N[:, 0] - L_m
    s = max(R @ np.array([0, 0, -1.0]), 0) ** 3
    expected = 0.5 * 0.2 + (0.9 * d + 0.3 * s) * np.array([1.0, 0.5, 0.25])
    assert I[:, 0] == pytest.approx(expected)


def test_unclamped_specular_reproduces_the_published_quirk():
    P = np.array([[0.0], [0.0], [0.02]])
    N = np.array([[1.0], [0.0], [0.0]])
    L = np.array([[[-0.6], [0.0], [-0.8]]])  # light from behind the surface: d = 0, R = -L, R.V = -0.8
    led = LED("l", (0, 0, 0), (0, 0, 1), (1.0, 1.0, 1.0), k_d=0.0, k_s=1.0)
    zero = np.zeros((3, 1))
    assert shade(P, N, L, [led], Material(ambient=0, shininess=2, clamp_specular=True), zero)[0, 0] == 0
    unclamped = shade(P, N, L, [led], Material(ambient=0, shininess=2, clamp_specular=False), zero)
    assert unclamped[0, 0] == pytest.approx(0.64)


def test_windowed_renderer_equals_the_whole_frame_chain(mesh, camera, spec, linear, rng):
    background = make_background("none", camera)
    renderer = Renderer.from_fields(spec, camera, linear, background)
    assert np.array_equal(renderer.render(linear.depth), renderer.base)
    shapes = [trimesh.primitives.Sphere(radius=0.004), trimesh.creation.box((0.005, 0.003, 0.004))]
    # Contacts in the middle and at the image's edges, where the window meets the border.
    for shape, pixel in zip(shapes * 2, [(250, 120), (330, 8), (600, 250), (180, 420)]):
        depth = press(linear.depth, camera, mesh, shape, pixel, 0.0015)
        fast = renderer.render(depth)
        full = render(depth, linear.depth, camera, spec, renderer.L, background)
        assert np.abs(fast - full).max() < 1e-5
        assert np.abs(fast - renderer.base).max() > 0.05  # the contact shows


def test_rendered_images_are_masked_and_in_range(mesh, camera, spec, linear):
    renderer = Renderer.from_fields(spec, camera, linear, make_background("none", camera))
    image = renderer.render(linear.depth)
    assert image.dtype == np.float32 and image.shape == (480, 640, 3)
    assert image.min() >= 0 and image.max() <= 1
    assert not image[~camera.mask].any()


def test_light_vectors_rectified_are_tangent(linear):
    L = light_vectors(linear, rectify=True)
    assert L.shape == (3, 3, 480, 640)
    ok = linear.valid[0] & (np.linalg.norm(linear.normals, axis=-1) > 0)
    dots = np.einsum("ihw,hwi->hw", L[0], linear.normals)[ok]
    assert np.abs(dots).max() < 1e-5
    assert np.allclose(np.linalg.norm(L[0], axis=0)[ok], 1, atol=1e-5)


def test_bad_render_inputs(camera, spec, linear, tmp_path):
    bg = make_background("none", camera)
    L = light_vectors(linear)
    with pytest.raises(ValueError, match=r"must be \(480, 640\) float"):
        render(np.zeros((480, 640, 3)), linear.depth, camera, spec, L, bg)
    nan = linear.depth.copy()
    nan[10, 10] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        render(nan, linear.depth, camera, spec, L, bg)
    with pytest.raises(ValueError, match="L must be"):
        render(linear.depth, linear.depth, camera, spec, L[:2], bg)
    with pytest.raises(ValueError, match="background must be"):
        render(linear.depth, linear.depth, camera, spec, L, np.zeros((240, 320, 3), np.float32))
    small = tmp_path / "small.png"
    write_rgb(small, np.zeros((240, 320, 3)))
    with pytest.raises(ValueError, match="must be 640x480"):
        make_background(str(small), camera)
    with pytest.raises(ValueError, match="colour"):
        make_background("solid", camera, colour=(2.0, 0, 0))


def test_png_round_trip(tmp_path):
    img = np.random.default_rng(0).integers(0, 256, (20, 30, 3)).astype(np.float32) / 255
    path = write_rgb(tmp_path / "a.png", img)
    assert np.array_equal(read_rgb(path), img)
    (tmp_path / "bad.png").write_bytes(b"not a png")
    with pytest.raises(ValueError, match="could not be read"):
        read_rgb(tmp_path / "bad.png")
