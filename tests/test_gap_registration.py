"""Registration of real frames on simulated ones (``studies.gap.registration``): known
turns and shifts recovered on synthetic frames whose contacts sit elsewhere in each
frame, the catalogue's convention, and the frames no match can be found on."""

import math

import numpy as np
import pytest
from skimage.transform import EuclideanTransform, warp

from studies.gap import effects as fx
from studies.gap.registration import MIN_CORRELATION, register, register_contacts, representative

SHAPE = (120, 160)
CENTRE = (59.5, 79.5)  # (row, col): the catalogue turns about the principal point


def membrane(rng: np.random.Generator) -> np.ndarray:
    """(H, W) a smooth lit membrane inside a black image circle."""
    v, u = np.mgrid[0:SHAPE[0], 0:SHAPE[1]].astype(np.float64)
    image = 0.35 + 0.15 * np.sin(u / 11.0 + 0.3) * np.cos(v / 9.0) + 0.1 * np.exp(-((u - 50) ** 2 + (v - 40) ** 2) / 300)
    circle = np.hypot(u - CENTRE[1], v - CENTRE[0]) < 56
    return np.where(circle, image, 0.0)


def with_contacts(image: np.ndarray, rng: np.random.Generator, count: int) -> np.ndarray:
    """``count`` frames, each with a bright dent of its own at a random place."""
    v, u = np.mgrid[0:SHAPE[0], 0:SHAPE[1]].astype(np.float64)
    out = []
    for _ in range(count):
        cu, cv = rng.uniform(40, 120), rng.uniform(30, 90)
        dent = 0.4 * np.exp(-((u - cu) ** 2 + (v - cv) ** 2) / (2 * 6.0**2))
        out.append(np.clip(image + dent * (image > 0), 0, 1))
    return np.stack(out)


def moved(frames: np.ndarray, turn_rad: float, shift_xy: tuple[float, float]) -> np.ndarray:
    """Each frame turned by ``turn_rad`` about the centre and shifted, by scikit-image's
    warp (not the catalogue's OpenCV remap): out(x) = in(T^-1 x), T x = R (x - c) + c + t."""
    c = np.array([CENTRE[1], CENTRE[0]])
    T = (EuclideanTransform(translation=-c) + EuclideanTransform(rotation=turn_rad)
         + EuclideanTransform(translation=c + np.asarray(shift_xy)))
    return np.stack([warp(f, T.inverse, order=3, mode="constant", cval=0.0) for f in frames]).astype(np.float32)


@pytest.mark.parametrize("turn_deg, shift", [(3.2, (10.0, -4.0)), (-4.0, (-7.0, 9.5)), (0.0, (12.0, 0.0)),
                                             (2.0, (0.0, 0.0))])
def test_known_turns_and_shifts_are_recovered_through_contacts(turn_deg, shift):
    rng = np.random.default_rng(7)
    base = membrane(rng)
    sim = with_contacts(base, rng, 12)
    real = moved(with_contacts(base, rng, 12), math.radians(turn_deg), shift)  # contacts elsewhere
    r, what = representative(real)
    s, _ = representative(sim)
    got = register(r, s, factor=2, centre=CENTRE, frames=what)
    assert got.reliable and got.correlation >= MIN_CORRELATION, got
    assert got.frames == "median of 12 frames"
    # real(x) = sim(T^-1 x): the catalogue's x_s = c + R(-turn) (x - c) - R(-turn) t, in
    # full-resolution pixels (factor 2).
    back = -math.radians(turn_deg)
    R = np.array([[math.cos(back), -math.sin(back)], [math.sin(back), math.cos(back)]])
    expected = -R @ np.asarray(shift) * 2
    assert got.rotation_rad == pytest.approx(back, abs=math.radians(0.15))
    assert [got.du_px, got.dv_px] == pytest.approx(expected.tolist(), abs=0.6)
    # The catalogue's own model, at the registered move, takes the simulated frames onto the real ones.
    coords = fx.source_coordinates(SHAPE, 100.0, CENTRE, {**got.params(), "du_px": got.du_px / 2,
                                                          "dv_px": got.dv_px / 2, "scale": 1.0}, None)
    back_on = fx.resample(np.repeat(s[None, ..., None], 3, axis=-1), coords)[0, ..., 0]
    inner = (slice(20, -20), slice(30, -30))
    assert np.abs(back_on - r)[inner].mean() < 0.1 * np.abs(s - r)[inner].mean() + 1e-3


def test_no_contact_frames_are_preferred_when_there_are_some():
    rng = np.random.default_rng(1)
    frames = with_contacts(membrane(rng), rng, 5)
    image, what = representative(frames, np.array([False, True, False, True, False]))
    assert what == "median of 2 no-contact frame(s)"
    assert np.allclose(image, np.median(frames[[1, 3]], axis=0))


@pytest.mark.parametrize("case, reason", [("flat", "flat"), ("saturated", "clipped")])
def test_a_frame_with_nothing_to_match_says_so_and_starts_at_zero(case, reason):
    image = np.full(SHAPE, 0.5, np.float32) if case == "flat" else np.ones(SHAPE, np.float32)
    got = register(image, image, frames="test")
    assert not got.reliable and reason in got.reason
    assert got.params() == {"du_px": 0.0, "dv_px": 0.0, "rotation_rad": 0.0}


def test_unrelated_frames_are_not_a_reliable_match():
    rng = np.random.default_rng(3)
    real, sim = (np.clip(0.5 + 0.2 * rng.standard_normal(SHAPE), 0, 1).astype(np.float32) for _ in range(2))
    got = register(real, sim)
    assert not got.reliable and ("correlates" in got.reason or "converge" in got.reason), got


def test_bad_input_is_refused_by_name():
    with pytest.raises(ValueError, match="one shape"):
        register(np.zeros(SHAPE), np.zeros((10, 10)))
    with pytest.raises(ValueError, match="NaN"):
        register(np.full(SHAPE, np.nan), np.zeros(SHAPE))


def test_a_round_solid_frame_is_turned_by_its_contacts():
    """A solid membrane in a round circle turns without a trace but in its contacts: the
    median frames' registration cannot see the turn, the contacts' correspondences can;
    a pair whose real contact differs from its simulated one is left out by RANSAC."""
    rng = np.random.default_rng(5)
    v, u = np.mgrid[0:SHAPE[0], 0:SHAPE[1]].astype(np.float64)
    solid = np.where(np.hypot(u - CENTRE[1], v - CENTRE[0]) < 56, 0.45, 0.0)
    sim = with_contacts(solid, rng, 16)
    turn, shift = math.radians(-3.5), (2.0, -1.5)
    real = moved(sim, turn, shift)
    real[3] = moved(with_contacts(solid, rng, 1), turn, shift)[0]  # a real contact somewhere else
    got = register_contacts(real, sim, factor=2, centre=CENTRE)
    assert got.reliable and "15 of 16 contacts agree" in got.frames, got
    back = -turn
    R = np.array([[math.cos(back), -math.sin(back)], [math.sin(back), math.cos(back)]])
    assert got.rotation_rad == pytest.approx(back, abs=math.radians(0.4))
    assert [got.du_px, got.dv_px] == pytest.approx((-R @ np.asarray(shift) * 2).tolist(), abs=0.8)
    few = register_contacts(real[:2], sim[:2])
    assert not few.reliable and "fewer than" in few.reason


def test_the_report_gives_each_registration_beside_the_fit():
    """The Answer's line: every registration (the contacts' has no correlation), or why
    it is unreliable, then the fit."""
    from studies.gap.registration import Registration
    from studies.gap.report import registration_line

    found = {"frame": Registration(0.01, -9.8, 4.6, 0.999, True, "", "median of 10 frames").to_dict(),
             "contacts": Registration(0.02, -9.5, 4.4, None, True, "", "the contacts of 10 pairs").to_dict(),
             "membrane": Registration(reason="the frames are flat", frames="median of 10 frames").to_dict()}
    entry = {"params": {"misalignment": {"du_px": -9.7, "dv_px": 4.5, "rotation_rad": 0.015, "scale": 1.0}},
             "fit_status": {"registration": found}}
    line = registration_line(entry)
    assert "frame (median of 10 frames): turn +0.57 deg, shift (-9.8, +4.6) px, correlation 0.999" in line
    assert "contacts (the contacts of 10 pairs): turn +1.15 deg" in line and "membrane (median of 10 frames): the frames are flat" in line
    assert line.endswith("The fit: turn +0.86 deg, shift (-9.7, +4.5) px, scale 1.0000.")
    assert registration_line({"params": {"blur_noise": {"sigma_px": 1.0}}, "fit_status": {}}) == ""
