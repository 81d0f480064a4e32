"""The benchmark's mechanisms written unlike the catalogue: their analytic limits, their
agreement with independent code, their draws, and their independence from the catalogue."""

import math
from pathlib import Path

import numpy as np
import pytest

from scenes.camera import reference_depth
from studies.gap import unlike
from studies.gap.inject_image import misalign

ROOT = Path(__file__).resolve().parents[1]


def test_the_response_curve_is_rational_and_the_matrix_general():
    image = np.array([[[0.0, 0.5, 1.0]]], np.float32)
    assert np.array_equal(unlike.matrix_curve(image, np.eye(3), [0.0, 0.0, 0.0]), image)
    # y (1 + b) / (1 + b y), b = -0.5: 0 -> 0, 0.5 -> 1/3, 1 -> 1.
    assert unlike.matrix_curve(image, np.eye(3), [-0.5] * 3)[0, 0].tolist() == pytest.approx([0, 1 / 3, 1])
    mixed = unlike.matrix_curve(np.array([[[0.2, 0.4, 0.6]]]), [[1, -0.5, 0], [0, 1, 0.5], [2, 0, 0]], [0, 0, 0])
    assert mixed[0, 0].tolist() == pytest.approx([0.0, 0.7, 0.4])  # clipped below 0
    with pytest.raises(ValueError, match="bend"):
        unlike.matrix_curve(image, np.eye(3), [-1.0, 0, 0])


def test_the_fade_follows_the_height_along_the_sensor(spec, mesh, camera):
    ref = reference_depth(mesh, camera)[0]
    height = unlike.axial_height(ref, camera, spec)
    tip = spec.membrane.base_z + spec.membrane.cylinder_length + spec.membrane.radius  # the LEDs are at z = 0
    assert height[240, 320] == pytest.approx(tip, abs=2e-4)  # the tip's apex, on the axis
    assert height[0, 0] == 0.0 and height[camera.mask].min() > 0.0
    image = np.full(camera.shape + (3,), 0.6, np.float32)
    faded = unlike.axial_fade(image, height, 0.05)
    assert faded[240, 320].tolist() == pytest.approx([0.6 * math.exp(-((tip / 0.05) ** 2))] * 3, rel=2e-3)
    assert np.array_equal(faded[~camera.mask], image[~camera.mask])  # z = 0 there
    with pytest.raises(ValueError, match="length_m"):
        unlike.axial_fade(image, height, 0.0)


def test_turning_the_frame_agrees_with_opencv():
    """scipy's cubic resampling and the injector's OpenCV warp, written apart, agree on a
    smooth image away from the border; a whole-pixel shift is a roll."""
    v, u = np.mgrid[0:120, 0:160].astype(np.float32)
    image = np.stack([0.5 + 0.4 * np.sin(u / 9.0) * np.cos(v / 7.0), 0.5 + 0.3 * np.cos(u / 13.0),
                      0.2 + 0.001 * (u + v)], axis=-1).astype(np.float32)
    centre = (79.5, 59.5)
    ours = unlike.turn_frame(image, math.radians(3.0), 4.0, -2.5, centre)
    theirs = misalign(image, 4.0, -2.5, math.radians(3.0), centre)
    inner = (slice(15, -15), slice(15, -15))
    assert np.abs(ours[inner] - theirs[inner]).max() < 0.01
    rolled = unlike.turn_frame(image, 0.0, 3.0, 0.0, centre)
    assert np.allclose(rolled[:, 3:], image[:, :-3], atol=1e-5) and np.all(rolled[:, :3] == 0)


def test_draws_stay_in_their_ranges_and_are_seeded(spec, mesh, camera):
    for name in unlike.MECHANISMS:
        a = unlike.sample_params(name, 0.5, np.random.default_rng(3))
        assert a == unlike.sample_params(name, 0.5, np.random.default_rng(3))
    p = unlike.sample_params("colour_matrix_curve", 1.0, np.random.default_rng(0))
    assert all(-0.3 <= p[f"m_{o}{i}"] <= 0.3 for o in "rgb" for i in "rgb" if o != i)
    assert all(-0.6 * 1.2 <= p[f"bend_{c}"] < 0 for c in "rgb")
    assert unlike.sample_params("fade_all_light", 0.5, np.random.default_rng(0))["length_m"] == pytest.approx(0.055)
    turn = unlike.sample_params("frame_turn", 0.5, np.random.default_rng(0))
    assert abs(turn["rotation_rad"]) == pytest.approx(math.radians(3.0))
    assert math.hypot(turn["shift_x_px"], turn["shift_y_px"]) == pytest.approx(6.0)
    with pytest.raises(ValueError, match="mechanism"):
        unlike.sample_params("sparkle", 0.5, np.random.default_rng(0))
    with pytest.raises(ValueError, match="strength"):
        unlike.sample_params("frame_turn", 1.5, np.random.default_rng(0))
    ref = reference_depth(mesh, camera)[0]
    plain = np.full(camera.shape + (3,), 0.5, np.float32) * camera.mask[..., None]
    written = unlike.Unlike(spec, ref)
    for name in unlike.MECHANISMS:
        out = written.apply(plain, name, unlike.sample_params(name, 0.5, np.random.default_rng(1)))
        assert out.shape == plain.shape and out.dtype == plain.dtype
        assert np.abs(out - plain)[camera.mask].mean() > 0.01, name


def test_the_mechanisms_import_nothing_from_the_diagnosis(absolute_imports):
    for name in absolute_imports(ROOT / "studies" / "gap" / "unlike.py"):
        assert not (name == "studies.gap" or name.startswith("studies.gap.")), name


def test_a_moved_frame_is_drawn_over_the_whole_range_at_any_strength():
    """frame_move draws its turn and shift at random over the whole range (issue 74: a
    turn up to 4 degrees, a shift up to 12 px), not one value per strength."""
    draws = [unlike.sample_params("frame_move", s, np.random.default_rng(k)) for k in range(60) for s in (0.0, 1.0)]
    turns = np.degrees([d["rotation_rad"] for d in draws])
    shifts = np.hypot([d["shift_x_px"] for d in draws], [d["shift_y_px"] for d in draws])
    assert np.abs(turns).max() <= unlike.MOVE_TURN_DEG and shifts.max() <= unlike.MOVE_SHIFT_PX
    assert turns.min() < -3.0 and turns.max() > 3.0 and shifts.min() < 3.0 and shifts.max() > 10.0
    assert len({round(t, 6) for t in turns}) == len(turns) // 2  # the strength does not change a seed's draw
