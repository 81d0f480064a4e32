"""The camera's lens in the spec: projection, distortion and principal point, honoured by
the ray-cast depth (both renderers' geometry), the MuJoCo depth camera and the
reference's film, and refused where it cannot image the tube."""

from __future__ import annotations

import dataclasses
import math
import tomllib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from scenes.camera import (Camera, lens_angle, lens_radius, lens_resample, pinhole_view, project,
                           reference_depth)
from scenes.shapes import family
from scenes.spec import DEFAULT_SPEC_PATH
from scenes.spec_read import spec_from_dict

#: MuJoCo's lens capture against the ray-cast D_ref, metres RMS (tests/test_rig.py's bound).
NO_CONTACT_RMS_BOUND_M = 0.1e-3


def _cosine(camera):
    """(H, W) the cosine of each pixel's ray's angle off the axis: smooth, analytic."""
    x, y = camera.slopes()
    return 1.0 / np.sqrt(1.0 + x * x + y * y)


def _lens(spec, **camera):
    return spec.replace(camera=dataclasses.replace(spec.camera, **camera))


@settings(max_examples=40, deadline=None)
@given(st.sampled_from(["pinhole", "fisheye"]), st.floats(-0.15, 0.3), st.floats(-0.02, 0.05),
       st.floats(math.radians(40), math.radians(150)), st.floats(-30, 30), st.floats(-30, 30))
def test_each_pixels_ray_projects_back_to_it(projection, k1, k2, fov, du, dv):
    if projection == "pinhole":
        fov = min(fov, math.radians(120))
    theta = lens_angle(np.array([0.0]), k1, k2, projection)
    assert theta[0] == 0.0
    camera = Camera(160, 120, 1.0, 79.5 + du, 59.5 + dv, 60.0, 80.0, 60.0, k1, k2, projection)
    reach = float(lens_radius(fov / 2, k1, k2, projection))
    if not reach > 0 or not np.isfinite(lens_angle(np.array([reach]), k1, k2, projection))[0]:
        return  # a lens that folds inside this field of view: the spec refuses it (below)
    camera = dataclasses.replace(camera, f=60.0 / reach)
    x, y = camera.slopes()
    seen = np.isfinite(x) & camera.mask
    uv = project(camera.rays, camera)
    v, u = np.mgrid[0:120, 0:160]
    assert np.allclose(uv[..., 0][seen], u[seen], atol=1e-3) and np.allclose(uv[..., 1][seen], v[seen], atol=1e-3)


def test_the_field_of_view_and_the_equidistant_fisheye(spec):
    for projection, fov in (("pinhole", math.radians(90)), ("fisheye", math.radians(135)),
                            ("fisheye", math.radians(170))):
        camera = Camera.from_spec(_lens(spec, projection=projection, fov_y=fov).camera)
        # the ray seen half the frame's height above the principal point is fov / 2 off the axis
        x, y = camera.slopes(np.array(camera.cx), np.array(camera.cy - camera.height / 2))
        assert math.atan(math.hypot(float(x), float(y))) == pytest.approx(fov / 2, abs=1e-6)
    # an equidistant fisheye: angle proportional to the distance from the principal point
    camera = Camera.from_spec(_lens(spec, projection="fisheye", fov_y=math.radians(135)).camera)
    r = np.linspace(0, 230, 24)
    x, y = camera.slopes(camera.cx + r, np.full_like(r, camera.cy))
    assert np.allclose(np.arctan(np.hypot(x, y)), r / camera.f, atol=1e-6)
    # a barrel sees further out than its pinhole at the same focal length, a pincushion less
    barrel = dataclasses.replace(camera, projection="pinhole", k1=-0.1)
    pincushion = dataclasses.replace(barrel, k1=0.1)
    plain = dataclasses.replace(barrel, k1=0.0)
    u = np.array(camera.cx + 200.0)
    v = np.array(camera.cy)
    assert barrel.slopes(u, v)[0] > plain.slopes(u, v)[0] > pincushion.slopes(u, v)[0]


def test_a_principal_point_off_the_frames_centre_moves_the_tube(spec):
    plain = Camera.from_spec(spec)
    moved = Camera.from_spec(_lens(spec, principal_point_px=(300.0, 250.0)).camera)
    tip = np.array([0.0, 0.0, family(spec.membrane.shape).tube(spec.membrane).apex_z])
    assert project(tip, plain) == pytest.approx([319.5, 239.5])
    assert project(tip, moved) == pytest.approx([300.0, 250.0])
    # the scaled camera keeps it, at pixel centres
    assert (moved.scaled(160, 120).cx, moved.scaled(160, 120).cy) == pytest.approx((74.625, 62.125))


def test_the_planned_bilinear_read_is_scipys(spec, rng):
    """lens_resample's kept plan reads what scipy.ndimage.map_coordinates(order=1,
    mode="nearest") reads, for one plane or several, float32 or float64."""
    from scipy import ndimage

    lens = Camera.from_spec(_lens(spec, projection="fisheye", fov_y=math.radians(150),
                                  principal_point_px=(310.0, 245.0)).camera)
    cover = lens.pinhole_cover()
    coords = np.stack([cover.cy + cover.f * lens.rays[..., 1], cover.cx + cover.f * lens.rays[..., 0]])
    for image in (rng.random(cover.shape).astype(np.float32), rng.random(cover.shape + (3,))):
        planes = image.reshape(cover.shape + (-1,))
        want = np.stack([ndimage.map_coordinates(planes[..., c], coords, order=1, mode="nearest")
                         for c in range(planes.shape[-1])], axis=-1).reshape(image.shape)
        got = lens_resample(image, lens, cover)
        assert got.dtype == image.dtype and got.shape == lens.shape + image.shape[2:]
        np.testing.assert_allclose(got, want, atol=1e-6)
    # other modes still go through scipy
    assert lens_resample(np.ones(cover.shape), lens, cover, mode="constant", cval=7.0).max() == 7.0


def test_the_pinhole_cover_holds_every_ray_of_the_image_circle(spec):
    lens = Camera.from_spec(_lens(spec, projection="fisheye", fov_y=math.radians(135),
                                  principal_point_px=(310.0, 245.0)).camera)
    cover = lens.pinhole_cover()
    assert cover.is_pinhole and (cover.cx, cover.cy) == (319.5, 239.5) and cover.f < lens.f
    plain = Camera.from_spec(spec)
    assert plain.pinhole_cover() is plain
    # an image the cover sees, read into the lens: the cosine of the angle off the axis
    seen = lens_resample(_cosine(cover), lens, cover)
    assert np.abs(seen - _cosine(lens))[lens.mask].max() < 2e-4  # bilinear reading
    # a barrel that folds outside its image circle, inside the frame: the frame's corners
    # see no ray, and still read finite values (a depth map must be finite everywhere)
    barrel = Camera(640, 480, 343.0, 319.5, 239.5, 240.0, 320.0, 240.0, k1=-0.3)
    assert np.isnan(barrel.slopes()[0]).any() and np.isfinite(barrel.slopes()[0][barrel.mask]).all()
    assert np.isfinite(lens_resample(np.ones(barrel.shape), barrel, barrel.pinhole_cover())).all()
    # and back: a mask drawn in the lens' pixels, read at the cover's
    back = pinhole_view(lens.mask, lens, cover)
    assert back.any() and np.abs(np.arctan(np.hypot(*cover.slopes()))[back]).max() <= math.radians(135) / 2 * 1.3


@pytest.mark.parametrize("camera", [dict(principal_point_px=(300.0, 250.0), distortion=(-0.08, 0.005)),
                                    dict(projection="fisheye", fov_y=math.radians(135)),
                                    dict(offset_m=(0.001, -0.0005), tilt_rad=(0.03, -0.02))])
def test_mujoco_depth_through_the_lens_matches_the_ray_cast(spec, camera, mujoco_gl):
    from scenes.geometry import membrane_mesh
    from scenes.indenters import indenter
    from scenes.rig import Rig, rig_scene

    lens_spec = _lens(spec, **camera)
    mesh = membrane_mesh(lens_spec)
    lens = Camera.from_spec(lens_spec)
    ref = reference_depth(mesh, lens)[0]
    try:
        rig = Rig(rig_scene(lens_spec, {"sphere": indenter("sphere")}, membrane=mesh), lens_spec)
        rig.mount("sphere")
        rig.home()
        depth = rig.depth()
    except RuntimeError as exc:
        pytest.skip(f"no headless GL context: {exc}")
    rig.close()
    rms = float(np.sqrt(np.mean((depth - ref)[lens.mask].astype(np.float64) ** 2)))
    assert rms < NO_CONTACT_RMS_BOUND_M
    # not the plain camera's depth map: the lens, or the seat, moved what each pixel sees
    plain = reference_depth(membrane_mesh(spec), Camera.from_spec(spec))[0]
    assert float(np.sqrt(np.mean((plain - ref)[lens.mask] ** 2))) > 20 * rms


def test_the_references_film_is_read_through_the_lens(spec):
    from pbr_tactile.estimate import Estimate
    from pbr_tactile.render import sensor_effects
    from pbr_tactile.effects import Effects
    from pbr_tactile.scene import geltip_scene

    lens_spec = _lens(spec, projection="fisheye", fov_y=math.radians(135), principal_point_px=(310.0, 245.0))
    lens = Camera.from_spec(lens_spec).scaled(160, 120)
    cover = lens.pinhole_cover()
    scene = geltip_scene({k: "x.ply" for k in ("coating", "core", "base", "glass_inner", "glass_base")},
                         lens_spec, Camera.from_spec(lens_spec), Effects(), 160, 120)
    assert scene["sensor"]["fov"] == pytest.approx(math.degrees(2 * math.atan(60.0 / cover.f)))
    # a film of each pixel's cosine off the axis comes out as the lens' pixels' cosines
    film = np.repeat(_cosine(cover).astype(np.float32)[..., None], 3, axis=-1)
    est = sensor_effects(Estimate(mean=film, variance=np.zeros_like(film), spp=1), Camera.from_spec(lens_spec),
                         Effects())
    assert np.abs(est.mean[..., 0] - _cosine(lens))[lens.mask].max() < 2e-3


def _data():
    return tomllib.loads(DEFAULT_SPEC_PATH.read_text())


@pytest.mark.parametrize(
    "camera, message",
    [
        (dict(fov_y=math.radians(5)), r"camera.fov_y must be in \[0.1745, 2.9671\]"),
        (dict(fov_y=math.radians(175), projection="fisheye"), r"fov_y must be in"),
        (dict(distortion=[1.5, 0.0]), r"distortion \(k1, k2\) must each lie in \[-1.0, 1.0\]"),
        (dict(distortion=[0.0]), "distortion must be a list of 2"),
        (dict(distortion=[-0.4, 0.0], fov_y=math.radians(120)), "folds the pinhole lens back at 42.4 deg"),
        (dict(projection="orthographic"), "projection must be one of"),
        (dict(principal_point_px=[700.0, 240.0]), r"principal_point_px \[700.0, 240.0\] must lie in the 640x480"),
        (dict(principal_point_px=[600.0, 240.0]), r"puts the tube's tip at pixel \(600.0, 240.0\), outside"),
        (dict(mask_radius_px=0.0), "mask_radius_px must be > 0"),
        (dict(offset_m=[0.007, 0.001]), r"outside its bore \(radius 0.007 m"),
        (dict(offset_m=[3.0, 0.0]), "not millimetres"),
        (dict(offset_m=[0.001, 0.0], _mesh=True), "a membrane.mesh_path mesh is already in the camera frame"),
        (dict(tilt_rad=[0.0, 0.3]), r"tilt_rad \[0.0, 0.3\] must each lie in \[-0.2618, 0.2618\]"),
    ],
)
def test_a_lens_that_cannot_image_the_tube_is_refused(camera, message):
    data, camera = _data(), dict(camera)
    if camera.pop("_mesh", False):
        data["membrane"] = {"shape": "mesh", "mesh_path": "membrane.stl", "thickness": 0.0025}
    data["camera"].update(camera)
    with pytest.raises(ValueError, match=message):
        spec_from_dict(data, "test.toml")


def test_a_lens_spec_round_trips(spec):
    data = _data()
    data["camera"].update(principal_point_px=[310.0, 245.0], distortion=[-0.05, 0.002], projection="fisheye",
                          fov_y=math.radians(135))
    lens_spec = spec_from_dict(data, "test.toml")
    import json

    again = spec_from_dict(json.loads(json.dumps(dataclasses.asdict(lens_spec))), "again")
    assert again == lens_spec and again.digest() != spec.digest()


def test_the_fast_paths_point_cloud_lies_on_the_membrane_through_the_lens(spec):
    """The fast path shades P = D * ray (``back_project``): through a lens, each pixel's
    point must be the membrane point its ray meets, and project back to that pixel."""
    from scenes.camera import back_project
    from scenes.geometry import membrane_mesh

    lens_spec = _lens(spec, projection="fisheye", fov_y=math.radians(135), distortion=(-0.05, 0.0))
    mesh = membrane_mesh(lens_spec)
    lens = Camera.from_spec(lens_spec).scaled(160, 120)
    depth, valid = reference_depth(mesh, lens)
    P = back_project(depth.astype(np.float64), lens)
    inside = valid & lens.mask
    r = np.hypot(P[..., 0], P[..., 1])[inside]
    z = P[..., 2][inside]
    m = lens_spec.membrane
    top = m.base_z + m.cylinder_length  # the dome's centre
    off = np.where(z <= top, r, np.hypot(r, z - top)) - m.radius
    assert np.abs(off).max() < 0.05e-3  # the capsule's mesh is faceted at 0.5 mm edges
    v, u = np.nonzero(inside)
    assert np.allclose(project(P[inside], lens), np.c_[u, v], atol=1e-6)


def test_the_tube_is_seated_against_the_camera_as_the_spec_says(spec):
    """The camera's offset and tilt move the tube (membrane, glass) in the camera frame;
    the LEDs stay on the camera's crown, and the reference places them against the tube."""
    from pbr_tactile.scene import led_centres, led_places
    from scenes.geometry import membrane_mesh
    from scenes.spec import LED

    tilt = (0.02, -0.03)
    seated = _lens(spec, offset_m=(0.001, -0.0005), tilt_rad=tilt)
    mesh, plain = membrane_mesh(seated), membrane_mesh(spec)
    # the apex: the tube's axis point at tip_z, seen from the offset, tilted camera
    ax, ay = tilt
    rx = np.array([[1, 0, 0], [0, math.cos(ax), -math.sin(ax)], [0, math.sin(ax), math.cos(ax)]])
    ry = np.array([[math.cos(ay), 0, math.sin(ay)], [0, 1, 0], [-math.sin(ay), 0, math.cos(ay)]])
    apex = (rx @ ry).T @ (np.array([0.0, 0.0, family(spec.membrane.shape).tube(spec.membrane).apex_z]) - [0.001, -0.0005, 0.0])
    top = np.asarray(plain.vertices)[np.argmax(np.asarray(plain.vertices)[:, 2])]
    moved = np.asarray(mesh.vertices)[np.argmax(np.asarray(plain.vertices)[:, 2])]
    assert np.allclose(top, [0, 0, family(spec.membrane.shape).tube(spec.membrane).apex_z], atol=1e-9) and np.allclose(moved, apex, atol=1e-9)
    assert mesh.is_watertight == plain.is_watertight and len(mesh.faces) == len(plain.faces)
    # an LED 6.5 mm either side of the camera, offset 1 mm along x: 5.5 mm and 7.5 mm from
    # the tube's axis, in the bore (7 mm) and under the glass wall
    led = dict(direction=(0.0, 0.0, 1.0), colour=(1.0, 0.0, 0.0), k_d=1.0, k_s=0.0)
    two = seated.replace(camera=dataclasses.replace(seated.camera, offset_m=(0.001, 0.0), tilt_rad=(0.0, 0.0)),
                         leds=(LED("a", position=(-0.0065, 0.0, -0.003), **led),
                               LED("b", position=(0.0065, 0.0, -0.003), **led)))
    assert led_places(two) == ["tube", "wall_end"]
    centres = led_centres(two)
    assert centres[0] == pytest.approx([-0.0065, 0.0, -0.003])
    # under the wall: at mid-wall (8 mm from the tube's axis), 7 mm from the camera's
    assert centres[1][0] == pytest.approx(0.008 - 0.001)
