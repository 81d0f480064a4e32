"""The flat GelSight: the pad membrane (analytic first), its spec and body, the ball
indenter, the protocols and the rig on it, and the fast path's demo."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from scenes.shapes import pad
from scenes.spec_read import load_spec

GELSIGHT = "scenes/sensors/gelsight.toml"
#: Distances below this are rounding, metres (the profile is sampled at 257 points).
TOL_M = 1e-6


@pytest.fixture(scope="module")
def gelsight():
    return load_spec(Path(__file__).resolve().parents[1] / GELSIGHT)


# --- the pad: analytic ------------------------------------------------------------------------


def test_pad_sag_and_profile_are_a_spherical_cap():
    p = {"radius": 0.012, "dome_radius": 0.05}
    assert pad.sag(p) == pytest.approx(0.05 - math.sqrt(0.05**2 - 0.012**2))
    assert pad.rim_slope(p) == pytest.approx(math.asin(0.012 / 0.05))
    prof = pad.profile(p, 0.03)
    centre_z = 0.03 + pad.sag(p) - 0.05
    np.testing.assert_allclose(np.hypot(prof[:, 0], prof[:, 1] - centre_z), 0.05, atol=1e-12)
    assert tuple(prof[0]) == (0.012, 0.03) and prof[-1, 0] == 0 and prof[-1, 1] == pytest.approx(0.03 + pad.sag(p))


def test_pad_mesh_is_one_sheet_on_the_sphere_open_at_its_rim():
    from scenes.shapes.mesh import base_loop, check_membrane

    p = {"radius": 0.012, "dome_radius": 0.05}
    mesh = pad.shape_mesh(p, 0.03, 0.5e-3)
    check_membrane(mesh)  # one oriented manifold sheet, open at its base alone, normals out
    V = np.asarray(mesh.vertices)
    centre = np.array([0.0, 0.0, 0.03 + pad.sag(p) - 0.05])
    np.testing.assert_allclose(np.linalg.norm(V - centre, axis=1), 0.05, atol=TOL_M)
    rim = V[base_loop(mesh)]
    np.testing.assert_allclose(rim[:, 2], 0.03, atol=TOL_M)
    np.testing.assert_allclose(np.hypot(rim[:, 0], rim[:, 1]), 0.012, atol=TOL_M)
    apex = np.argmax(V[:, 2])
    np.testing.assert_allclose(mesh.vertex_normals[apex], [0, 0, 1], atol=1e-3)  # out of the elastomer: +z


@pytest.mark.parametrize("params, match", [
    ({"radius": 0.05}, r"membrane\.params\.radius = 0\.05 m is outside its bounds \[0\.003, 0\.04\] m"),
    ({"dome_radius": float("nan")}, r"membrane\.params\.dome_radius must be finite \(metres\), got nan"),
    ({"width": 0.01}, r"unknown parameter 'width' for a 'pad' membrane; expected some of radius, dome_radius"),
    ({"radius": "wide"}, r"membrane\.params\.radius must be a number \(metres\), got 'wide'"),
    ({"radius": 0.02, "dome_radius": 0.021}, r"slopes 72 deg at its rim, over 60 deg"),
])
def test_pad_refuses_bad_parameters(params, match):
    with pytest.raises(ValueError, match=match):
        pad.check_params(params)


def test_pad_mesh_refuses_a_bad_edge():
    with pytest.raises(ValueError, match=r"edge must be in \(0, 0\.00325\] m"):
        pad.shape_mesh({}, 0.03, 0.004)


# --- the spec and its body ---------------------------------------------------------------------


def test_gelsight_spec_body_and_camera(gelsight):
    from scenes.body import sensor_body
    from scenes.camera import Camera, reference_depth
    from scenes.geometry import membrane_mesh

    assert gelsight.membrane.shape == "pad" and dict(gelsight.membrane.params)["dome_radius"] == 0.05
    mesh = membrane_mesh(gelsight)
    body = sensor_body(gelsight, mesh)
    np.testing.assert_allclose(body.thickness, 2.5e-3, atol=1e-6)  # a cap offset inwards by less than its radius
    assert 0.15 <= body.seen_share < 0.2  # the 22 mm pad reaches past the view, to its LEDs
    camera = Camera.from_spec(gelsight)
    assert camera.mask.all()  # no image circle: the whole frame sees gel
    depth, seen = reference_depth(mesh, camera)
    assert seen.all()
    # A pixel spans the published 0.031125 mm (0.1245 mm at 160x120) where the axis meets the gel.
    assert depth[240, 320] / camera.f == pytest.approx(0.1245e-3 / 4, rel=1e-3)
    assert len(gelsight.leds) == 3 and [led.name for led in gelsight.leds] == ["red", "green", "blue"]


def _pad_spec(tmp_path, radius_m):
    """The GelSight with its pad's rim at ``radius_m``, the rim plane moved so the apex
    stays where the camera's scale puts it, the LEDs 1 mm outside the rim."""
    import dataclasses

    from scenes.spec import LED

    spec = load_spec(Path(__file__).resolve().parents[1] / GELSIGHT)
    params = dict(spec.membrane.params)
    apex = spec.membrane.base_z + pad.sag(params)
    params["radius"] = radius_m
    base_z = apex - pad.sag(params)
    leds = tuple(dataclasses.replace(led, position=tuple(np.r_[np.asarray(led.position[:2]) / np.linalg.norm(
        led.position[:2]) * (radius_m + 1e-3), base_z - 1e-3])) for led in spec.leds if isinstance(led, LED))
    membrane = dataclasses.replace(spec.membrane, params=tuple(params.items()) if isinstance(
        spec.membrane.params, tuple) else params, base_z=base_z)
    return dataclasses.replace(spec, membrane=membrane, leds=leds)


def test_a_pad_may_reach_past_the_view_but_must_cover_it(tmp_path):
    """A flat sensor's gel reaches past what its camera sees, to the LEDs at its edge: a
    22 mm pad, of which the camera sees 17 %, is a body (no MIN_SEEN_SHARE for pads); a
    pad that leaves the frame's corners without gel is refused, naming the rays."""
    from scenes.body import MIN_SEEN_SHARE, sensor_body

    wide = sensor_body(_pad_spec(tmp_path, 0.022))
    assert 0.1 < wide.seen_share < MIN_SEEN_SHARE
    with pytest.raises(ValueError, match=r"rays of the camera \(at 64x48\) miss the membrane: the image would show "
                                         r"no gel there; widen the pad"):
        sensor_body(_pad_spec(tmp_path, 0.009))


def test_spec_at_a_resolution_scales_the_camera_and_the_smoothing(gelsight):
    from scenes.camera import Camera

    small = gelsight.at_resolution(160, 120)
    big, little = Camera.from_spec(gelsight), Camera.from_spec(small)
    assert (little.width, little.height) == (160, 120) and little.f == pytest.approx(big.f / 4)
    assert small.camera.mask_center_px == (79.5, 59.5) and small.camera.mask_radius_px == pytest.approx(400.5 / 4)
    assert small.elastic.sigma_px == pytest.approx(23.0 / 4) and small.elastic.radius_px == 17
    assert small.camera.fov_y == gelsight.camera.fov_y
    with pytest.raises(ValueError, match=r"a 160x100 frame has another aspect ratio than the 640x480 camera"):
        gelsight.at_resolution(160, 100)


def test_protocols_press_the_pad_along_its_normal_and_within_its_thickness(gelsight):
    from scenes.geometry import membrane_mesh
    from scenes.protocol import base_protocol, extended_protocol

    mesh = membrane_mesh(gelsight)
    base = base_protocol(gelsight, mesh, ["ball_4mm", "cone"])
    assert len(base) == 36
    points = np.array([t.point for t in base.taps])
    normals = np.array([t.normal for t in base.taps])
    assert np.all(normals[:, 2] > 0.98)  # the domed pad faces the object: +z, tilted a few degrees
    assert np.all(np.array([t.depth for t in base.taps]) <= 2.5e-3)
    assert np.abs(points[:, :2]).max() < 0.0099  # every contact inside the 19.9 x 14.9 mm the camera sees
    extended = extended_protocol(gelsight, mesh, ["ball_4mm"], replicas=2)
    assert len(extended) == 5 * 16 * 2


# --- the ball ----------------------------------------------------------------------------------


def test_ball_names_and_their_meshes():
    from scenes.indenters import BALL_DIAMETER_BOUNDS_M, ball_diameter, ball_name, indenter, is_indenter

    assert ball_name(4e-3) == "ball_4mm" and ball_name(6.35e-3) == "ball_6.35mm"
    assert ball_diameter("ball_4mm") == pytest.approx(4e-3) and ball_diameter("ball_6.35mm") == pytest.approx(6.35e-3)
    for bad in ("ball_04mm", "ball_x", "ball_4", "ball_100mm", "sphere"):
        assert ball_diameter(bad) is None, bad
    assert is_indenter("ball_4mm") and not is_indenter("ball_100mm")
    mesh = indenter("ball_4mm")
    assert mesh.is_watertight and mesh.volume > 0
    V = np.asarray(mesh.vertices)
    top = V[V[:, 2] > V[:, 2].max() - 1.5e-3]  # the cap it presses with: on a 2 mm sphere
    centre = np.array([0.0, 0.0, V[:, 2].max() - 2e-3])
    np.testing.assert_allclose(np.linalg.norm(top - centre, axis=1), 2e-3, atol=1e-5)
    with pytest.raises(ValueError, match=r"a ball's diameter must be in \[0\.5, 16\] mm, got 40 mm"):
        ball_name(0.04)
    with pytest.raises(ValueError, match=r"a ball \(ball_<diameter>mm, e\.g\. ball_4mm\)"):
        indenter("ball_4cm")
    assert BALL_DIAMETER_BOUNDS_M[1] == pytest.approx(16e-3)


# --- the rig and the renderers on the flat sensor ----------------------------------------------


def test_the_rig_presses_the_ball_as_deep_as_the_tap_says(gelsight, mujoco_gl):
    from scenes.camera import Camera
    from scenes.generate import measured_depth
    from scenes.geometry import membrane_mesh
    from scenes.protocol import base_protocol
    from scenes.rig import tap_depths

    small = gelsight.at_resolution(160, 120)
    mesh = membrane_mesh(small)
    taps = [t for t in base_protocol(small, mesh, ["ball_4mm"]).taps][::5]
    replay = tap_depths(small, taps)
    ref = next(replay)[0]
    camera = Camera.from_spec(small)
    for tap, (depth, _) in zip(taps, replay):
        # the deepest pixel's indentation: within a pixel's sag of the ball (0.1245 mm
        # pixels on a 2 mm ball: under 4 um) and the depth map's float rounding
        assert measured_depth(depth, ref, camera, tap, 1e-6) == pytest.approx(tap.depth, abs=2e-5)


def test_the_layer_holds_the_pads_rim_so_a_press_near_it_builds_a_closed_solid(gelsight):
    """A press near the frame's edge moves the membrane within eight decay lengths of the
    pad's rim; the layer holds the rim (its base) still, so the dented elastomer closes on
    the undeformed base ring (the reference refused such solids as self-crossing)."""
    from scenes.camera import Camera, reference_depth
    from scenes.contact import press
    from scenes.elastic import MembraneLayer
    from scenes.geometry import membrane_mesh
    from scenes.shapes.mesh import base_loop

    import trimesh

    small = gelsight.at_resolution(160, 120)
    mesh = membrane_mesh(small)
    camera = Camera.from_spec(small)
    ref = reference_depth(mesh, camera)[0]
    depth = press(ref, camera, mesh, trimesh.primitives.Sphere(radius=0.002), (25, 60), 0.0012)
    layer = MembraneLayer(mesh, small, camera)
    result = layer.deformation(depth, ref)
    rim = base_loop(layer.mesh)
    assert result.displacement.max() == pytest.approx(1.2e-3, abs=0.05e-3)
    assert np.all(result.displacement[rim] == 0.0)


@pytest.mark.slow  # 15 to 22 s alone on 2 cores
def test_the_demo_renders_the_flat_sensor(tmp_path, session_env, capsys):
    from scenes.cli import main

    assert main(["demo", "--spec", str(Path(__file__).resolve().parents[1] / GELSIGHT), "--out", str(tmp_path)]) == 0
    assert (tmp_path / "contact_sheet.png").stat().st_size > 10_000
    assert len(list((tmp_path / "images").glob("linear_*.png"))) == 8  # 4 contacts x 2 backgrounds
