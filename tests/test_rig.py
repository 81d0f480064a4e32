"""The MuJoCo tapping rig: names, headless depth on the spec's camera, geometric contact."""

from __future__ import annotations

import math

import numpy as np
import pytest

from scenes.camera import reference_depth
from scenes.gl import GLPlatformError, choose_gl
from scenes.protocol import base_protocol

#: The issue's bound on a no-contact capture against the ray-cast D_ref, metres RMS.
NO_CONTACT_RMS_BOUND_M = 0.1e-3
#: Measured indentation (deepest pixel along the normal) against the commanded depth.
DEPTH_TOLERANCE_M = 0.05e-3


@pytest.fixture(scope="module")
def rig_factory(spec, mesh, mujoco_gl):
    from scenes.indenters import indenter
    from scenes.rig import Rig, rig_scene

    from scenes.indenters import INDENTERS

    try:
        rig = Rig(rig_scene(spec, {name: indenter(name) for name in ("sphere",) + INDENTERS}, membrane=mesh), spec)
        rig.depth()
    except RuntimeError as exc:
        pytest.skip(f"no headless GL context: {exc}")

    def make(name="sphere"):
        rig.mount(name)
        return rig

    yield make
    rig.close()


@pytest.fixture(scope="module")
def ref(mesh, camera):
    return reference_depth(mesh, camera)[0]


def test_everything_is_named(rig_factory):
    rig = rig_factory()
    m = rig.model
    for joint in ("printer_x", "printer_y", "printer_z", "indenter_pitch", "sensor_roll"):
        assert m.joint(joint).name == joint
        assert m.actuator(joint).name == joint
    for body in ("sensor", "printer_head", "indenter_servo", "indenter"):
        assert m.body(body).name == body
    for geom in ("membrane", "membrane_view", "glass_core", "indenter_sphere", "indenter_cone", "printer_bed"):
        assert m.geom(geom).name == geom
    assert m.camera("geltip_depth").name == "geltip_depth"
    assert m.site("indenter_tip_sphere").name == "indenter_tip_sphere"
    assert 'name="geltip_depth"' in rig.scene.xml


def test_no_contact_depth_matches_the_ray_cast_reference(rig_factory, camera, ref):
    rig = rig_factory()
    rig.home()
    depth = rig.depth()
    assert depth.shape == camera.shape and depth.dtype == np.float32
    err = (depth - ref)[camera.mask].astype(np.float64)
    rms = float(np.sqrt(np.mean(err**2)))
    print(f"MuJoCo no-contact vs ray-cast D_ref: RMS {rms * 1e3:.6f} mm")
    assert rms < NO_CONTACT_RMS_BOUND_M
    # The same holds with the sensor rolled: the camera rolls with it.
    rig.set_joints(sensor_roll=1.0)
    assert np.sqrt(np.mean((rig.depth() - ref)[camera.mask] ** 2)) < NO_CONTACT_RMS_BOUND_M


@pytest.mark.parametrize("name", ["sphere", "cylinder", "cone", "dots", "open_cylinder", "pacman", "indented_prism", "random"])
def test_measured_indentation_equals_the_commanded_depth(rig_factory, spec, mesh, camera, ref, name):
    from scenes.generate import measured_depth

    rig = rig_factory(name)
    protocol = base_protocol(spec, mesh, (name,))
    for tap in protocol.taps[::5]:
        rig.press(tap)
        depth = rig.depth()
        assert (depth < ref - 1e-6).sum() > 20, f"tap {tap.index} left no imprint"
        got = measured_depth(depth, ref, camera, tap, 1e-6)
        assert got == pytest.approx(tap.depth, abs=DEPTH_TOLERANCE_M), f"tap {tap.index} ({name})"


def test_a_capture_is_one_render_of_membrane_and_indenter(rig_factory, spec, mesh):
    """Rig.depth keeps the membrane's depth and renders the indenter alone: what one
    render of both gives, to float32 rounding, on taps of every kind of indenter."""
    from scenes.rig import DEPTH_GROUPS

    for name in ("sphere", "indented_prism", "open_cylinder"):
        rig = rig_factory(name)
        for tap in base_protocol(spec, mesh, (name,)).taps[::6]:
            rig.press(tap)
            both = rig._depth_of(DEPTH_GROUPS)
            np.testing.assert_allclose(rig.depth(), both, rtol=0, atol=1e-7)
            assert (both < rig._membrane_depth - 1e-4).any()  # the indenter is in the view


def test_pose_puts_the_indenter_where_the_tap_says(rig_factory, spec, mesh):
    rig = rig_factory()
    tap = base_protocol(spec, mesh, ("sphere",)).taps[0]  # the apex, from +X
    pose = rig.tap_pose(tap)
    assert pose["indenter_pitch"] == pytest.approx(math.pi / 2)
    rig.set_joints(**pose)
    R, t = rig.sensor_to_world()
    tip = np.array(rig.data.site("indenter_tip_sphere").xpos)
    apex = R @ np.asarray(tap.point) + t
    # The sphere's top point is 2 mm inside the apex, on the axis.
    assert np.allclose(tip, apex - 0.002 * (R @ np.asarray(tap.normal)), atol=1e-6)


def test_the_kinematics_chain_is_the_mujoco_rigs(rig_factory):
    """scenes.kinematics puts the indenter where MuJoCo's forward kinematics does, at any
    joints: the real rig, which has no MuJoCo, drives the head by the same chain."""
    from scenes.kinematics import indenter_to_world, sensor_to_world

    rig = rig_factory()
    rng = np.random.default_rng(0)
    for _ in range(5):
        head = rng.uniform((0.0, -0.1, 0.1), (0.3, 0.1, 0.3))
        pitch, roll = rng.uniform(-0.3, 1.8), rng.uniform(-0.1, 3.2)
        rig.set_joints(printer_x=head[0], printer_y=head[1], printer_z=head[2], indenter_pitch=pitch, sensor_roll=roll)
        R, t = indenter_to_world(head, pitch, rig.layout)
        body = rig.data.body("indenter")
        assert np.allclose(R, np.array(body.xmat).reshape(3, 3), atol=1e-12)
        assert np.allclose(t, body.xpos, atol=1e-12)
        R_s, t_s = rig.sensor_to_world()
        assert np.allclose(R_s, sensor_to_world(roll), atol=1e-12)
        assert np.allclose(t_s, rig.layout.sensor_origin, atol=1e-12)


def test_mounting_swaps_what_the_camera_sees(rig_factory, spec, mesh, camera, ref):
    rig = rig_factory("sphere")
    tap = base_protocol(spec, mesh, ("sphere",)).taps[0]
    rig.press(tap)
    sphere = rig.depth()
    from dataclasses import replace

    rig.press(replace(tap, object="cylinder"))
    cylinder = rig.depth()
    assert rig.mounted == "cylinder"
    # At 2 mm the 5 mm sphere cuts a wider cap out of the curved apex than the 3 mm cylinder.
    area_sphere, area_cylinder = (sphere < ref - 1e-6).sum(), (cylinder < ref - 1e-6).sum()
    assert area_sphere > 1.1 * area_cylinder > 0
    with pytest.raises(ValueError, match="not in this rig"):
        rig.mount("teapot")


def test_out_of_travel_is_refused(rig_factory):
    rig = rig_factory()
    with pytest.raises(ValueError, match="outside its travel"):
        rig.set_joints(printer_z=5.0)
    with pytest.raises(ValueError, match="sensor_roll"):
        rig.set_joints(sensor_roll=4.0)


def test_snapshot_and_export(rig_factory, tmp_path):
    import mujoco

    rig = rig_factory()
    image = rig.snapshot(320, 240)
    assert image.shape == (240, 320, 3) and image.std() > 0.05
    path = rig.scene.export(tmp_path / "scene")
    model = mujoco.MjModel.from_xml_path(str(path))
    assert model.camera("geltip_depth").name == "geltip_depth"


def test_missing_gl_platform_names_the_packages(monkeypatch):
    monkeypatch.delenv("MUJOCO_GL", raising=False)
    with pytest.raises(GLPlatformError, match="libegl1 libegl-mesa0 libgl1-mesa-dri"):
        choose_gl(find_library=lambda name: None)
    monkeypatch.setenv("MUJOCO_GL", "egl")
    with pytest.raises(GLPlatformError, match="libEGL is missing"):
        choose_gl(find_library=lambda name: None)
