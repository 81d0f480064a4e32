"""The DIGIT and the GelSight Mini: their specs load with their sourced values, their
bodies cover the view, and the fast path renders a pressed ball on each."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from scenes.spec_read import load_spec

SENSORS = Path(__file__).resolve().parents[1] / "scenes" / "sensors"
#: name -> (width, height px, fov_y rad, mm a pixel where the axis meets the gel, LEDs)
SOURCED = {
    # digit-interface's QVGA frames as get_frame() gives them (transposed: portrait);
    # TACTO's 60 deg vertical field of view, its gel 22 mm from the camera
    "digit": (240, 320, math.radians(60.0), 2 * 22.0 * math.tan(math.radians(30.0)) / 320, 3),
    # the SDKs' 320 x 240 frames at 0.0634 mm a pixel (gsrobotics show3d.py, gs_sdk gsmini.yaml)
    "gelsight_mini": (320, 240, 2 * math.atan(120 * 0.0634 / 24.0), 0.0634, 3),
}


@pytest.fixture(scope="module", params=sorted(SOURCED))
def sensor(request):
    from scenes.camera import Camera
    from scenes.geometry import membrane_mesh

    spec = load_spec(SENSORS / f"{request.param}.toml")
    return request.param, spec, membrane_mesh(spec), Camera.from_spec(spec)


def test_the_specs_hold_their_sourced_values(sensor):
    from scenes.camera import reference_depth

    name, spec, mesh, camera = sensor
    width, height, fov_y, mm_per_px, leds = SOURCED[name]
    assert spec.name == name and spec.membrane.shape == "pad"
    assert (spec.camera.width, spec.camera.height) == (width, height)
    assert spec.camera.fov_y == pytest.approx(fov_y, rel=1e-9)
    assert len(spec.leds) == leds and [led.name for led in spec.leds] == ["red", "green", "blue"]
    assert camera.mask.all()  # no image circle: the whole frame sees gel
    depth, seen = reference_depth(mesh, camera)
    assert seen.all()  # the pad fills the view (scenes.shapes.pad FILLS_VIEW)
    assert depth[height // 2, width // 2] / camera.f * 1e3 == pytest.approx(mm_per_px, rel=1e-3)
    thickness = spec.membrane.thickness
    sigma_mm = thickness * math.sqrt((1 - spec.elastic.poisson_ratio) / 6) * 1e3
    assert spec.elastic.sigma_px == pytest.approx(sigma_mm / mm_per_px, abs=0.05)
    assert abs(spec.elastic.radius_px - 3 * spec.elastic.sigma_px) <= 1


def test_the_digit_frames_are_portrait_and_the_minis_landscape():
    digit = load_spec(SENSORS / "digit.toml").camera
    mini = load_spec(SENSORS / "gelsight_mini.toml").camera
    assert digit.height > digit.width and mini.width > mini.height


def test_the_fast_path_renders_a_pressed_ball(sensor):
    import trimesh

    from phong_reference.background import make_background
    from phong_reference.bake import bake
    from phong_reference.render import light_vectors, render
    from scenes.camera import reference_depth
    from scenes.contact import press

    name, spec, mesh, camera = sensor
    ref = reference_depth(mesh, camera)[0]
    L = light_vectors(bake(mesh, camera, spec.leds, "linear", use_cache=False))
    background = make_background("solid", camera)
    centre = ((camera.width - 1) / 2, (camera.height - 1) / 2)
    dent = press(ref, camera, mesh, trimesh.creation.icosphere(subdivisions=3, radius=0.002), centre, 0.001)
    assert (ref - dent).max() == pytest.approx(0.001, abs=5e-5)
    still, pressed = (render(d, ref, camera, spec, L, background) for d in (ref, dent))
    assert still.shape == pressed.shape == (camera.height, camera.width, 3)
    assert np.isfinite(pressed).all() and 0.0 <= pressed.min() and pressed.max() <= 1.0
    change = np.abs(pressed - still).sum(axis=2)
    v, u = np.unravel_index(np.argmax(change), change.shape)
    # the ball (2 mm radius, 1 mm deep: a 1.7 mm contact radius) changes the image round it,
    # and leaves the frame's corners alone
    reach_px = 2.5e-3 / (ref[int(centre[1]), int(centre[0])] / camera.f)
    assert math.hypot(u - centre[0], v - centre[1]) < reach_px, name
    assert change.max() > 0.05
    assert change[:10, :10].max() < 1e-3 and change[-10:, -10:].max() < 1e-3
