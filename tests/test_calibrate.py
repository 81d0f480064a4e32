"""Calibration: the sensor profile (scenes.profile) and the reference's image fit
(pbr_tactile.calibrate), analytic cases first; one small end-to-end run with Mitsuba."""

from __future__ import annotations

import json
import dataclasses
import math

import numpy as np
import pytest

from pbr_tactile import calibrate as cal
from pbr_tactile import image_fit as imf
from pbr_tactile import image_model as im
from pbr_tactile import real_image as ri
from pbr_tactile.calibrate_capture import real_background
from scenes.image_stats import r2
from scenes.profile import (
    PROFILE_VERSION,
    Alignment,
    CameraProfile,
    Profile,
    load_profile,
    write_profile,
)
from scenes.spec_read import default_spec
from tests.fake_basis import each_variant_traced


def _profile(spec, **camera):
    return Profile(sensor=spec.name, leds=tuple(led.name for led in spec.leds), alignment=Alignment(0.1, 1.05, (2, -3)),
                   camera=CameraProfile(gamma=1.8, vignetting=(-0.3, 0.0), image_circle=(320, 240, 240), **camera),
                   reference={"led_gains": [[1.0, 0.5, 0.2]] * 3}, fit={"converged": True})


# -- the profile ----------------------------------------------------------------------------

def test_profile_round_trip(tmp_path, spec):
    profile = _profile(spec)
    path = write_profile(profile, tmp_path / "profile.toml")
    again = load_profile(path, spec)
    assert again == profile


def test_profile_for_another_sensor_is_refused(tmp_path, spec):
    path = write_profile(_profile(spec), tmp_path / "profile.toml")
    other = default_spec()
    import dataclasses

    other = dataclasses.replace(other, name="another")
    with pytest.raises(ValueError, match="is for sensor"):
        load_profile(path, other)


@pytest.mark.parametrize("change, message", [
    ({"gamma": 9.0}, "camera.gamma"),
    ({"vignetting": (-2.0, 0.0)}, "relative illumination negative"),
    ({"offset": (0.0, -0.1, 0.0)}, "camera.offset"),
    ({"image_circle": (320.0, 240.0, -1.0)}, "radius must be > 0"),
])
def test_profile_out_of_physical_bounds_is_refused(change, message):
    with pytest.raises(ValueError, match=message):
        CameraProfile(**change)


def test_corrupt_or_old_profile_is_refused(tmp_path, spec):
    bad = tmp_path / "bad.toml"
    bad.write_text("this is = = not toml")
    with pytest.raises(ValueError, match="not valid TOML"):
        load_profile(bad)
    path = write_profile(_profile(spec), tmp_path / "p.toml")
    path.write_text(path.read_text().replace(f"version = {PROFILE_VERSION}", "version = 0"))
    with pytest.raises(ValueError, match="version"):
        load_profile(path)
    with pytest.raises(FileNotFoundError, match="does not exist"):
        load_profile(tmp_path / "missing.toml")


# -- the real image -----------------------------------------------------------------------

def _disc(camera, centre=(322.0, 236.0), radius=230.0, value=0.5):
    v, u = np.mgrid[0:camera.height, 0:camera.width]
    inside = np.hypot(u - centre[0], v - centre[1]) <= radius
    return np.where(inside[..., None], value, 0.0) * np.ones(3)


def test_image_circle_is_found(camera):
    cx, cy, radius = ri.image_circle(_disc(camera))
    assert abs(cx - 322) < 0.5 and abs(cy - 236) < 0.5 and abs(radius - 230) < 1.0
    assert ri.image_circle(np.full((camera.height, camera.width, 3), 0.4)) is None


def test_bad_real_images_are_refused(camera):
    with pytest.raises(ValueError, match="640x480 RGB"):
        ri.check_real(np.zeros((240, 320, 3)), camera)
    with pytest.raises(ValueError, match="blank"):
        ri.check_real(np.zeros((camera.height, camera.width, 3)), camera)
    with pytest.raises(ValueError, match="saturated almost everywhere"):
        ri.check_real(np.ones((camera.height, camera.width, 3)), camera)
    nan = _disc(camera)
    nan[0, 0, 0] = np.nan
    with pytest.raises(ValueError, match="finite"):
        ri.check_real(nan, camera)


def test_real_background_inputs(tmp_path):
    with pytest.raises(ValueError, match="exactly one"):
        real_background(None, None)
    with pytest.raises(ValueError, match="exactly one"):
        real_background(str(tmp_path), "x.png")
    with pytest.raises(FileNotFoundError, match="no dataset.json"):
        real_background(str(tmp_path), None)
    (tmp_path / "dataset.json").write_text(json.dumps({"source": "sim"}))
    with pytest.raises(ValueError, match="source 'sim'"):
        real_background(str(tmp_path), None)
    (tmp_path / "dataset.json").write_text(json.dumps({"source": "real"}))
    with pytest.raises(ValueError, match="no background.png"):
        real_background(str(tmp_path), None)
    (tmp_path / "background.png").write_bytes(b"")
    assert real_background(str(tmp_path), None)[0] == tmp_path / "background.png"


# -- the image model and its fit ------------------------------------------------------------

def test_censored_gains_ignore_clipped_pixels_above_the_level():
    rng = np.random.default_rng(0)
    X = rng.uniform(0, 1, (400, 2))
    truth = np.array([0.9, 0.6])
    y = X @ truth + 0.05
    clipped = y >= ri.CLIP_LEVEL
    assert 20 < clipped.sum() < 380
    gains, offset = im.solve_gains(X, np.minimum(y, ri.CLIP_LEVEL), clipped, gamma=1.0)
    np.testing.assert_allclose(gains, truth, atol=1e-6)
    assert abs(offset - 0.05) < 1e-6
    naive, _ = im.solve_gains(X, np.minimum(y, ri.CLIP_LEVEL), np.zeros_like(clipped), gamma=1.0)
    assert np.abs(naive - truth).max() > 0.02  # without censoring the clip pulls the gains down


def _synthetic_basis(h=60, w=80, camera=None):
    """Smooth per-source images: each LED lights the rim near its azimuth, its leak the
    middle ring; sources led0, led0_leak, led1, ..."""
    v, u = np.mgrid[0:h, 0:w].astype(float)
    s = h / camera.height
    cx, cy = (camera.cx + 0.5) * s - 0.5, (camera.cy + 0.5) * s - 0.5
    rho, phi = np.hypot(u - cx, v - cy) / (camera.mask_radius_px * s), np.arctan2(v - cy, u - cx)
    images, names = [], []
    for m, azimuth in enumerate((0.0, 2.1, 4.2)):
        images.append((0.1 + rho**2) * (1.2 + np.cos(phi - azimuth)) ** 2)
        images.append(np.exp(-((rho - 0.5) / 0.2) ** 2) * (1.1 + np.cos(phi - azimuth)))
        names += [f"led{m}", f"led{m}_leak"]
    return np.stack(images, -1), np.array(names)


def test_fit_recovers_hidden_parameters_of_a_synthetic_sensor(camera):
    A, names = _synthetic_basis(camera=camera)
    circle = (321.0, 241.0, 236.0)
    model = im.ImageModel(A, names, camera, circle)
    truth = im.Nonlinear(rotation_rad=0.7, led_azimuth_rad=(0.05, -0.08, 0.1), leak=(0.3, 0.5, 0.2), scale=1.05,
                          shift_px=(6.0, -4.0), vignetting=(-0.4, 0.0), gamma=1.8)
    gains = np.array([[0.5, 0.2, 0.6], [0.1, 0.4, 0.5], [0.3, 0.1, 0.9]]) * 0.6
    real = model.render(truth, gains, (0.01, 0.02, 0.0), (1.0, 1.0, ri.CLIP_LEVEL))
    sector = ri.sector_index(real.shape[:2], (40, 30))
    train, test = (sector % 2 == 0) & model.inside, (sector % 2 == 1) & model.inside
    fit = imf.ImageFitter(model, real, train).search(rotations=6)
    assert fit.converged
    pred = model.render(fit.nl, fit.gains, fit.offset, (1.0, 1.0, 1.0))
    for c in range(2):
        assert r2(pred[..., c], real[..., c], test) > 0.99
    # The three synthetic LEDs differ only in gains, so a turn by a third is the same
    # sensor with its LEDs renamed: the rotation is known modulo 2 pi / 3, the LEDs'
    # parameters up to that renaming; and only each LED's whole turn, the rotation plus
    # its azimuth, is seen (calibrate.NOT_IDENTIFIABLE).
    turn = fit.nl.rotation_rad - truth.rotation_rad
    shift = int(round(turn / (2 * math.pi / 3))) % 3
    whole_fit = fit.nl.rotation_rad + np.array(fit.nl.led_azimuth_rad)
    whole_true = truth.rotation_rad + np.array(truth.led_azimuth_rad) + shift * 2 * math.pi / 3
    for j in range(3):
        assert abs(math.remainder(whole_fit[j] - whole_true[(j + shift) % 3], 2 * math.pi)) < 0.05
    assert abs(fit.nl.gamma - 1.8) < 0.1
    assert abs(fit.nl.scale - 1.05) < 0.02
    np.testing.assert_allclose(np.roll(fit.nl.leak, shift), truth.leak, atol=0.08)


def test_a_known_alignment_is_held_and_keeps_each_leds_name(camera):
    """A sensor whose camera is the spec's (rotation 0, scale 1, no shift): held there,
    the fit moves none of them, recovers each LED's own azimuth and gains under its own
    name (a free search may rename the LEDs by a third of a turn, as above), and is
    refused with a fitted lens."""
    A, names = _synthetic_basis(camera=camera)
    circle = (321.0, 241.0, 236.0)
    model = im.ImageModel(A, names, camera, circle, known_alignment=True)
    n = model.leds
    bounds = model.bounds(True)
    for i in (0, 1 + 2 * n, 2 + 2 * n, 3 + 2 * n, len(bounds) - 1):
        assert bounds[i][0] == bounds[i][1], i
    assert bounds[1] == (-im.AZIMUTH_BOUND_RAD, im.AZIMUTH_BOUND_RAD)
    truth = im.Nonlinear(rotation_rad=0.0, led_azimuth_rad=(0.12, -0.08, 0.2), leak=(0.3, 0.5, 0.2), scale=1.0,
                          shift_px=(0.0, 0.0), vignetting=(-0.4, 0.0), gamma=1.8)
    gains = np.array([[0.5, 0.2, 0.6], [0.1, 0.4, 0.5], [0.3, 0.1, 0.9]]) * 0.6
    real = model.render(truth, gains, (0.01, 0.02, 0.0), (1.0, 1.0, 1.0))
    sector = ri.sector_index(real.shape[:2], (40, 30))
    train, test = (sector % 2 == 0) & model.inside, (sector % 2 == 1) & model.inside
    fit = imf.ImageFitter(model, real, train).search()
    assert fit.converged
    assert fit.nl.rotation_rad == 0.0 and fit.nl.scale == 1.0 and fit.nl.shift_px == (0.0, 0.0)
    np.testing.assert_allclose(fit.nl.led_azimuth_rad, truth.led_azimuth_rad, atol=0.02)
    np.testing.assert_allclose(fit.gains, gains, rtol=0.05, atol=0.01)
    pred = model.render(fit.nl, fit.gains, fit.offset, (1.0, 1.0, 1.0))
    assert min(r2(pred[..., c], real[..., c], test) for c in range(3)) > 0.99
    # a camera turned 1 rad from the spec's is not the spec's: held (the LEDs' azimuths
    # free only within AZIMUTH_BOUND_RAD), the fit cannot reach it (what --camera-known
    # asserts), and leaves a gap a free search closes
    turned = model.render(dataclasses.replace(truth, rotation_rad=1.0, led_azimuth_rad=(0.0, 0.0, 0.0)), gains,
                          (0.01, 0.02, 0.0), (1.0, 1.0, 1.0))
    held = imf.ImageFitter(model, turned, train).search()
    free = imf.ImageFitter(im.ImageModel(A, names, camera, circle), turned, train).search(rotations=6)
    assert held.loss > 10 * free.loss
    with pytest.raises(ValueError, match="known alignment"):
        im.ImageModel(A, names, camera, circle, lens=True, known_alignment=True)


def test_the_alignments_lens_is_the_cameras_lens(spec):
    """Another mechanism: an image of the membrane rendered by a camera with a barrel lens,
    a wider field and a moved principal point (``lens_resample`` of a pinhole's view) is
    the spec's pinhole image moved by the Alignment that says so."""
    from scenes.camera import Camera, lens_resample
    from scenes.profile import Alignment, align_image

    pinhole = Camera.from_spec(spec).scaled(160, 120)
    alignment = Alignment(0.0, 0.9, (6.0, -4.0), distortion=(-0.06, 0.0))
    real = alignment.lens(Camera.from_spec(spec)).scaled(160, 120)
    # a smooth pattern on the pinhole's view, wide enough to hold the lens' rays
    wide = dataclasses.replace(pinhole, f=pinhole.f / 1.5)
    x, y = wide.slopes()
    pattern = (x**3 - 3 * x * y**2) * np.exp(-(x**2 + y**2)) + 0.2 * x
    seen = lens_resample(pattern, real, wide)
    moved = alignment.sampling((120, 160), Camera.from_spec(spec), rendered=Camera.from_spec(spec).scaled(160, 120))
    assert moved.shape == (2, 120, 160)
    via = align_image(lens_resample(pattern, pinhole, wide), alignment, Camera.from_spec(spec))
    inside = real.mask & (moved[0] > 1) & (moved[0] < 118) & (moved[1] > 1) & (moved[1] < 158)
    assert inside.sum() > 8000
    assert np.abs(via - seen)[inside].max() < 0.02
    # and the forward map inverts the sampling
    v, u = np.nonzero(inside)
    uo, vo = alignment.moved(moved[1][v, u] * 4 + 1.5, moved[0][v, u] * 4 + 1.5, Camera.from_spec(spec))
    assert np.abs((uo + 0.5) / 4 - 0.5 - u).max() < 1e-6 and np.abs((vo + 0.5) / 4 - 0.5 - v).max() < 1e-6


def test_fit_recovers_a_lens_that_sees_wider_than_the_basis(camera):
    """The real lens a barrel (k1 < 0) of a shorter focal length than the spec's: fitted
    from a basis rendered wider (``basis_camera``), its k1 and scale come back."""
    from pbr_tactile.basis import basis_camera
    wide = basis_camera(camera)
    A, names = _synthetic_basis(45, 60, camera=camera)
    model = im.ImageModel(A, names, camera, (321.0, 241.0, 236.0), rendered=wide, lens=True)
    # it sees 1.18 focal lengths out at the circle's edge, which the basis holds (1.3)
    truth = im.Nonlinear(rotation_rad=0.4, led_azimuth_rad=(0.0, 0.0, 0.0), leak=(0.3, 0.5, 0.2), scale=0.92,
                          shift_px=(4.0, -3.0), vignetting=(-0.3, 0.0), gamma=1.6, k1=-0.06)
    gains = np.array([[0.5, 0.2, 0.6], [0.1, 0.4, 0.5], [0.3, 0.1, 0.9]]) * 0.5
    real = model.render(truth, gains, (0.01, 0.02, 0.0), (1.0, 1.0, 1.0))
    train = model.inside
    fit = imf.ImageFitter(model, real, train).fit(model.start(0.4, 0.3))
    assert fit.converged
    assert abs(fit.nl.k1 - truth.k1) < 0.005 and abs(fit.nl.scale - truth.scale) < 0.005
    held = im.ImageModel(A, names, camera, (321.0, 241.0, 236.0), rendered=wide)
    assert held.bounds(True)[-1] == (0.0, 0.0)  # without ``lens`` the spec's k1 is kept


def test_the_fitted_camera_reads_as_a_spec_states_it(spec, camera):
    """The report's camera: the spec's at the start; a focal length scaled by s is the
    field of view 2 atan(tan(fov / 2) / s), the shift moves the principal point."""
    model = im.ImageModel(*_synthetic_basis(camera=camera), camera, None, lens=True)
    nl = model.start()
    out = cal.fitted_camera(nl, camera)
    assert out["fov_y"] == pytest.approx(spec.camera.fov_y) and out["principal_point_px"] == [319.5, 239.5]
    moved = dataclasses.replace(nl, scale=0.8, shift_px=(3.0, -5.0), k1=0.0)
    out = cal.fitted_camera(moved, camera)
    assert out["fov_y"] == pytest.approx(2 * math.atan(math.tan(spec.camera.fov_y / 2) / 0.8))
    assert out["principal_point_px"] == [322.5, 234.5] and out["projection"] == "pinhole"
    # a barrel sees further out at the frame's edge than its pinhole
    assert cal.fitted_camera(dataclasses.replace(moved, k1=-0.05), camera)["fov_y"] > out["fov_y"]
    assert cal.fitted_camera(dataclasses.replace(moved, k1=-0.1), camera)["fov_y"] is None  # folds at 1.22 f
    # the scale on its search bound is named; no leak is a physical limit, not a search bound
    low = dataclasses.replace(nl, scale=im.SCALE_BOUNDS[0], leak=(0.0, 0.3, 0.3))
    bound = cal.on_bound(low, model, leak=True)
    assert bound["search"] == ["log_scale"] and "leak[0]" in bound["physical"]


@pytest.mark.slow
def test_grid_points_are_compared_without_their_own_monte_carlo_noise(camera, spec, monkeypatch):
    """The sensor's own point, rendered noisily, against a clean point that is slightly
    wrong: the raw loss prefers the clean one, the loss less the basis' predicted noise
    the right one; the prediction matches the noise the fit actually sees, after the
    basis is moved (bilinear interpolation averages its noise)."""
    pytest.importorskip("mitsuba")
    A, names = _synthetic_basis(camera=camera)
    sigma = 0.1 * A.mean()
    noisy = A + np.random.default_rng(0).normal(0.0, sigma, A.shape)
    u = np.arange(A.shape[1])[None, :, None]
    wrong = A * (1 + 0.05 * np.cos(u / 7.0))
    bases = {10.0: {"mean": noisy, "variance": np.full_like(A, sigma**2), "names": names,
                    "response": np.ones((len(names), 3))},
             50.0: {"mean": wrong, "variance": np.zeros_like(A), "names": names, "response": np.ones((len(names), 3))}}
    monkeypatch.setattr(cal, "emitter_basis", each_variant_traced(
        lambda spec_, mesh, camera_, effects, *a, **k: bases[effects.scattering_per_m]))
    # the calibration renders its no-contact basis wider than the camera (basis_camera)
    from pbr_tactile.basis import basis_camera

    model = im.ImageModel(A, names, camera, None, rendered=basis_camera(camera))
    truth = im.Nonlinear(rotation_rad=0.7, led_azimuth_rad=(0.0, 0.0, 0.0), leak=(0.3, 0.5, 0.2), scale=1.0,
                          shift_px=(0.0, 0.0), vignetting=(-0.3, 0.0), gamma=1.8)
    gains = np.array([[0.5, 0.2, 0.6], [0.1, 0.4, 0.5], [0.3, 0.1, 0.9]]) * 0.15  # nothing clipped
    k = camera.height // A.shape[0]
    real = np.repeat(np.repeat(model.render(truth, gains, (0, 0, 0), (1, 1, 1)), k, axis=0), k, axis=1)
    grid = {"absorption_per_m": (20.0,), "scattering_per_m": (10.0, 50.0)}
    result = cal.calibrate_background(real, spec, None, camera, film=(A.shape[1], A.shape[0]), grid=grid, bootstrap=0)
    own, clean = result.report["grid"]
    assert own["loss"] > 1.3 * clean["loss"] and clean["noise"] == 0.0
    assert own["noise"] == pytest.approx(own["loss"], rel=0.15)
    assert result.report["best_effects"]["scattering_per_m"] == 10.0


def test_a_fit_that_cannot_move_and_leaves_a_gap_is_not_converged(camera):
    A, names = _synthetic_basis(camera=camera)
    model = im.ImageModel(A, names, camera, None)
    rng = np.random.default_rng(1)
    real = rng.uniform(0.2, 0.8, (A.shape[0], A.shape[1], 3))  # no structure the model can follow
    fitter = imf.ImageFitter(model, real, model.inside)
    fit = fitter.fit(im.Nonlinear.start(3), max_evaluations=3)
    assert not fit.converged


# (the end-to-end run, with Mitsuba and a capture dataset's taps, is in test_calibrate_taps.py)


def test_calibrate_command_refuses_bad_input(tmp_path, capsys):
    from scenes.cli import main
    from scenes.images import write_rgb

    assert main(["calibrate", "--out", str(tmp_path / "o")]) == 1
    assert "exactly one of REAL" in capsys.readouterr().err
    small = tmp_path / "small.png"
    write_rgb(small, np.full((240, 320, 3), 0.5, np.float32))
    assert main(["calibrate", "--background-only", str(small), "--out", str(tmp_path / "o")]) == 1
    assert "must be 640x480" in capsys.readouterr().err
    assert main(["calibrate", "benchmark", "--out", str(tmp_path / "o")]) == 1
    assert "needs --json" in capsys.readouterr().err
    assert main(["calibrate", "--background-only", str(small), "--cases", "2", "--out", str(tmp_path / "o")]) == 1
    assert "--cases is an option of" in capsys.readouterr().err
    assert not (tmp_path / "o" / "profile.toml").exists()


def test_reference_with_a_profile_refuses_what_it_cannot_render(tmp_path, spec, capsys):
    from scenes.cli import main

    path = write_profile(_profile(spec), tmp_path / "profile.toml")
    depth = tmp_path / "d.npy"
    np.save(depth, np.zeros((2, 2)))
    assert main(["reference", str(depth), "--profile", str(path), "--estimator", "volpath", "--out", "x"]) == 1
    assert "--profile needs the photon estimator" in capsys.readouterr().err
    path.write_text(path.read_text().replace('name = "geltip"', 'name = "other"'))
    assert main(["reference", str(depth), "--profile", str(path), "--out", "x"]) == 1
    assert "is for sensor 'other'" in capsys.readouterr().err
