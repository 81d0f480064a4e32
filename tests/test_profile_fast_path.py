"""The calibrated unit's fast path: the background model, the unit's spec and alignment,
the profiled renderer and its dataset option (analytic checks first)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from scenes import background_model as bm
from scenes.camera import Camera, project
from scenes.profile import (
    Alignment,
    CameraProfile,
    Profile,
    align_image,
    circle_polar,
    write_profile,
)

CIRCLE = (322.0, 238.0, 235.0)


def _table(coefficients: np.ndarray) -> dict:
    return {"model": bm.MODEL, "harmonics": bm.HARMONICS, "radial_degree": bm.RADIAL_DEGREE,
            "coefficients": np.asarray(coefficients).tolist()}


def _profile(spec, alignment: Alignment | None = None, background=(0.4, 0.3, 0.9), phong=True) -> Profile:
    coefficients = np.zeros((3, (bm.RADIAL_DEGREE + 1) * (2 * bm.HARMONICS + 1)))
    coefficients[:, 0] = background
    return Profile(sensor=spec.name, leds=tuple(led.name for led in spec.leds), alignment=alignment or Alignment(),
                   camera=CameraProfile(image_circle=CIRCLE),
                   phong={"ambient": 1.0, "background": _table(coefficients)} if phong else {})


# -- the background model -------------------------------------------------------------------

def test_background_model_recovers_its_own_coefficients_from_half_the_sectors():
    rng = np.random.default_rng(0)
    shape, full = (120, 160), (480, 640)
    terms = (bm.RADIAL_DEGREE + 1) * (2 * bm.HARMONICS + 1)
    truth = rng.normal(0.0, 0.01, (3, terms))
    truth[:, 0] = 0.5
    image = bm.evaluate(_table(truth), CIRCLE, shape, full).astype(np.float64)
    r, theta = circle_polar(CIRCLE, shape, full)
    inside = r <= 1.0
    assert 0.0 < image[inside].min() and image[inside].max() < 1.0  # nothing clipped: the fit is exact
    even = (np.floor(np.mod(theta, 2 * math.pi) / (math.pi / 6)).astype(int) % 2 == 0) & inside
    table = bm.fit(image, CIRCLE, even, full)
    again = bm.evaluate(table, CIRCLE, shape, full)
    assert np.abs(again - image)[inside & ~even].max() < 1e-4  # the held-out half too
    assert np.all(again[~inside] == 0)


def test_background_model_leaves_clipped_pixels_out():
    shape, full = (60, 80), (480, 640)
    r, _ = circle_polar(CIRCLE, shape, full)
    inside = r <= 1.0
    truth = np.stack([0.2 + 1.2 * r**2, 0.2 + 0.5 * r**2, 0.3 + 0.1 * r], axis=-1)
    image = np.minimum(truth, 1.0)  # red clips in an outer ring: there it says only "at least 1"
    clipped = image >= 1.0
    assert clipped[..., 0][inside].mean() > 0.2 and not clipped[..., 1:][inside].any()
    table = bm.fit(image, CIRCLE, inside, full, clipped)
    r_full = np.asarray(table["coefficients"]) @ bm.design(r, _)[inside].T  # unclipped model values
    ring = clipped[..., 0][inside]
    assert np.abs(r_full[0] - truth[..., 0][inside])[~ring].max() < 3e-3  # the ring does not pull red down
    assert r_full[0][ring].min() > 1.0 - 3e-3  # and is predicted at least at the clip level
    assert np.abs(bm.evaluate(table, CIRCLE, shape, full) - image)[inside].max() < 3e-3
    # not censored, the ring at 1 bends the fit away from the truth
    plain = np.asarray(bm.fit(image, CIRCLE, inside, full)["coefficients"]) @ bm.design(r, _)[inside].T
    assert np.abs(plain[0] - truth[..., 0][inside])[~ring].max() > 0.01


@pytest.mark.parametrize("change, message", [
    ({"model": "spline"}, "model must be"),
    ({"coefficients": [[0.0] * 5] * 3}, "coefficients must be 3 rows of"),
    ({"harmonics": "many"}, "malformed"),
])
def test_malformed_background_tables_are_refused(change, message):
    table = {**_table(np.zeros((3, (bm.RADIAL_DEGREE + 1) * (2 * bm.HARMONICS + 1)))), **change}
    with pytest.raises(ValueError, match=message):
        bm.evaluate(table, CIRCLE, (30, 40), (480, 640))


# -- the unit's spec and alignment -----------------------------------------------------------

def test_turned_leds_and_align_image_turn_the_same_way(spec, camera):
    """An LED turned by a (Profile.sensor_spec) lands where align_image moves its image
    under a rotation of a: the two halves of an alignment agree on the sign."""
    a = 0.4
    profile = _profile(spec, Alignment(led_azimuth_rad=(a, 0.0, 0.0)))
    unit = profile.sensor_spec(spec)
    led, turned = np.array(spec.leds[0].position), np.array(unit.leds[0].position)
    assert np.linalg.norm(turned[:2]) == pytest.approx(np.linalg.norm(led[:2]))
    assert math.atan2(turned[1], turned[0]) - math.atan2(led[1], led[0]) == pytest.approx(a)
    # a point on the membrane above the LED, seen by the camera, turned both ways
    point = np.array([led[0] * 0.8, led[1] * 0.8, 0.02])
    point_turned = np.array([turned[0] * 0.8, turned[1] * 0.8, 0.02])
    u, v = project(point, camera)
    image = np.zeros(camera.shape)
    image[int(round(v)) - 2:int(round(v)) + 3, int(round(u)) - 2:int(round(u)) + 3] = 1.0
    moved = align_image(image, Alignment(rotation_rad=a), camera)
    vv, uu = np.unravel_index(np.argmax(moved), moved.shape)
    ut, vt = project(point_turned, camera)
    assert abs(uu - ut) <= 2 and abs(vv - vt) <= 2
    assert unit.camera.mask_center_px == CIRCLE[:2] and unit.camera.mask_radius_px == CIRCLE[2]


def test_sensor_spec_refuses_a_wrong_number_of_azimuths(spec):
    with pytest.raises(ValueError, match="led_azimuth_rad has 2 values for 3 LEDs"):
        _profile(spec, Alignment(led_azimuth_rad=(0.1, 0.2))).sensor_spec(spec)


def test_led_azimuths_beyond_a_half_turn_are_refused():
    with pytest.raises(ValueError, match="led_azimuth_rad"):
        Alignment(led_azimuth_rad=(4.0, 0.0, 0.0))


# -- the profiled renderer -------------------------------------------------------------------

@pytest.fixture(scope="module")
def contact(spec, camera, mesh):
    import trimesh

    from phong_reference.bake import bake
    from scenes.contact import press

    ref = bake(mesh, camera, spec.leds, "plane").depth
    return mesh, ref, press(ref, camera, mesh, trimesh.primitives.Sphere(radius=0.004),
                            (camera.cx + 20, camera.cy - 10), 0.0015, spin=0.3)


def test_profiled_renderer_is_the_fast_path_moved_onto_the_units_background(spec, camera, contact):
    from phong_reference.bake import bake
    from phong_reference.profiled import ProfiledRenderer
    from phong_reference.render import Renderer, light_vectors

    mesh, ref, depth = contact
    # identity alignment, black background: the fast path itself, cut by the unit's circle
    profile = _profile(spec, background=(0.0, 0.0, 0.0))
    L = light_vectors(bake(mesh, camera, spec.leds, "plane"))
    fast_path = Renderer(spec, camera, ref, L, np.zeros(camera.shape + (3,), np.float32))
    plain = fast_path.render(depth)
    fast = ProfiledRenderer(spec, ref, L, profile).render(depth)
    unit_mask = Camera.from_spec(profile.sensor_spec(spec)).mask
    both = unit_mask & camera.mask
    assert np.abs(fast - plain)[both].max() < 1e-5
    assert np.all(fast[~unit_mask] == 0)

    # turned and shifted, on a grey background: the contact's change is the plain one, moved
    alignment = Alignment(rotation_rad=0.3, scale=1.1, shift_px=(12.0, -7.0), led_azimuth_rad=(0.0, 0.0, 0.0))
    profile = _profile(spec, alignment, background=(0.3, 0.3, 0.3))
    renderer = ProfiledRenderer(spec, ref, L, profile)
    # without contact: the background plus the plane field's own faint no-contact shading, moved
    no_contact = np.clip(align_image(renderer._membrane.base, alignment, camera) + 0.3, 0, 1)
    assert np.abs(renderer.base - no_contact)[unit_mask].max() < 1e-6
    image = renderer.render(depth)
    whole = np.clip(align_image(renderer._membrane.render(depth), alignment, camera) + 0.3, 0, 1) * unit_mask[..., None]
    assert np.abs(image - whole).max() < 1e-6  # the window is the whole frame's
    change = np.abs(image - renderer.base).sum(axis=2) > 0.02
    v, u = np.nonzero(change)
    expected = align_image((np.abs(plain - fast_path.base).sum(axis=2) > 0.02).astype(float), alignment, camera)
    ve, ue = np.nonzero(expected > 0.5)
    assert abs(v.mean() - ve.mean()) < 3 and abs(u.mean() - ue.mean()) < 3


def test_phong_dataset_option_profile(tmp_path, spec, camera, mesh):
    from phong_reference import plugin

    path = write_profile(_profile(spec), tmp_path / "profile.toml")
    with pytest.raises(ValueError, match="a background or a profile, not both"):
        plugin.options_from({"profile": str(path), "background": "solid"})
    no_phong = write_profile(_profile(spec, phong=False), tmp_path / "no_phong.toml")
    with pytest.raises(ValueError, match="no phong.background table"):
        plugin.prepare(spec, mesh, camera, {"profile": str(no_phong)})
    settings = plugin.prepare(spec, mesh, camera, {"profile": str(path)})
    assert settings["background"] == "profile" and settings["profile_data"]["sensor"]["name"] == spec.name
    renderer = plugin.make_renderer(spec, mesh, camera, plugin.bake(mesh, camera, spec.leds, "plane").depth,
                                    {"profile": str(path)})
    assert np.abs(renderer.no_contact[240, 322] - [0.4, 0.3, 0.9]).max() < 0.01  # plus the faint plane shading

    # the diagnosis rebuilds the unit's chain from the dataset's recorded settings
    from studies.gap.model import FastModel

    model = FastModel(spec, settings, factor=4)
    assert model.profile is not None
    assert np.abs(model.B[60, 80] - [0.4, 0.3, 0.9]).max() < 1e-5


@pytest.mark.slow
def test_pbr_dataset_renders_the_calibrated_unit(tmp_path, monkeypatch, spec, mesh, camera, ref, pressed):
    """The pbr dataset renderer with a profile: per-source passes (frame, control and
    contacts), each image the unit's camera applied to them (calibrate.profiled_image)."""
    pytest.importorskip("mitsuba")
    from pbr_tactile import plugin
    from pbr_tactile.profiled import profiled_image
    from pbr_tactile.variant import choose_variant

    if not choose_variant().variant().startswith(("llvm_", "cuda_")):
        pytest.skip("the photon estimator needs a vectorised variant (apt-get install libllvm19)")
    monkeypatch.setenv("TACTILE_SIM_CACHE", str(tmp_path / "cache"))
    alignment = Alignment(rotation_rad=0.4, scale=1.05, shift_px=(6.0, -4.0), led_azimuth_rad=(0.1, -0.05, 0.0))
    profile = dataclasses.replace(
        _profile(spec, alignment), camera=CameraProfile(gamma=2.0, offset=(0.01, 0.0, 0.02), image_circle=CIRCLE),
        reference={"effects": {"absorption_per_m": 20.0, "scattering_per_m": 50.0}, "led_leak": [0.3, 0.2, 0.1],
                   "led_gains": [[2e-3, 5e-4, 2e-4], [4e-4, 1.5e-3, 4e-4], [2e-4, 3e-4, 2.5e-3]]})
    path = write_profile(profile, tmp_path / "profile.toml")
    options = {"film": [64, 48], "photons": 1 << 13, "camera_spp": 2, "max_passes": 2, "no_contact_runs": 1,
               "target_rse": 5.0, "profile": str(path)}
    settings = plugin.prepare(spec, mesh, camera, options)
    names = settings["sources"]
    assert names == ["led0", "led0_leak", "led1", "led1_leak", "led2", "led2_leak"]
    assert settings["exposure_gain"] is None and settings["profile_data"] == profile.to_dict()
    renderer = plugin.make_renderer(spec, mesh, camera, ref, options)
    out = renderer.render_sample(pressed)
    linear = out["arrays"]["linear"]
    assert linear.shape == out["arrays"]["variance"].shape == (480, 640, 6)
    unit_camera = Camera.from_spec(profile.sensor_spec(spec))
    np.testing.assert_allclose(out["image"], profiled_image(linear, names, profile, unit_camera), atol=1e-6)
    assert np.all(out["image"][~unit_camera.mask] == 0) and out["image"][unit_camera.mask].max() > 0.05
    # the contact's change shows where the alignment moves it
    change = np.abs(out["image"] - renderer.no_contact).sum(axis=2)
    v, u = np.nonzero(change > 0.5 * change.max())
    dent = align_image((np.abs(pressed - ref) > 1e-6).astype(float), alignment, camera)
    ve, ue = np.nonzero(dent > 0.5)
    assert abs(np.median(v) - ve.mean()) < 25 and abs(np.median(u) - ue.mean()) < 25
    # refused: a profile with the volpath estimator, or of another path
    with pytest.raises(ValueError, match="option profile needs estimator photons"):
        plugin.options_from({**options, "estimator": "volpath"}, camera)
    with pytest.raises(ValueError, match="option profile must be the path"):
        plugin.options_from({**options, "profile": 3}, camera)


def test_alignment_moved_is_what_sampling_inverts(camera):
    alignment = Alignment(rotation_rad=0.7, scale=1.2, shift_px=(15.0, -9.0))
    u, v = np.array([250.0, 320.0, 390.0]), np.array([180.0, 240.0, 300.0])
    uo, vo = alignment.moved(u, v, camera)
    coords = alignment.sampling(camera.shape, camera)
    rows, cols = np.rint(vo).astype(int), np.rint(uo).astype(int)
    # the aligned pixel nearest each moved point samples back within a pixel of the point
    assert np.abs(coords[0][rows, cols] - v).max() < 1.0 and np.abs(coords[1][rows, cols] - u).max() < 1.0


# -- the fast path's LED constants from taps ---------------------------------------------------

@pytest.mark.slow  # 15 to 22 s alone on 2 cores
def test_fast_path_led_constants_are_recovered_from_its_own_taps(spec, camera, contact):
    import trimesh

    from phong_reference.bake import bake
    from phong_reference.calibrate import fit_led_constants, phong_form
    from phong_reference.profiled import ProfiledRenderer
    from phong_reference.render import light_vectors
    from scenes.captures import RealTaps
    from scenes.contact import press

    mesh, ref, _ = contact
    alignment = Alignment(rotation_rad=0.2, scale=1.0, shift_px=(4.0, -3.0), led_azimuth_rad=(0.0, 0.0, 0.0))
    L = light_vectors(bake(mesh, camera, spec.leds, "plane"))
    truth = [{"k_d": 0.6, "k_s": 0.2, "colour": [1.0, 0.3, 0.1]}, {"k_d": 0.4, "k_s": 0.0, "colour": [0.2, 1.0, 0.5]},
             {"k_d": 0.8, "k_s": 0.1, "colour": [0.1, 0.4, 1.0]}]
    profile = _profile(spec, alignment, background=(0.2, 0.2, 0.3))
    unit = dataclasses.replace(profile, phong={**profile.phong, "leds": truth, "shininess": 20.0})
    renderer = ProfiledRenderer(spec, ref, L, unit)
    sphere = trimesh.primitives.Sphere(radius=0.004)
    pixels = [(camera.cx + 40, camera.cy - 20), (camera.cx - 60, camera.cy + 30), (camera.cx + 10, camera.cy + 70),
              (camera.cx - 30, camera.cy - 80)]
    depths = np.stack([press(ref, camera, mesh, sphere, p, 0.0015) for p in pixels]).astype(np.float32)
    taps = RealTaps(np.stack([renderer.render(d) for d in depths]), depths, ref, ["a", "b", "c", "d"])
    # the profile being calibrated has the spec's constants: the fit must find the unit's
    table, report = fit_led_constants(spec, camera, ref, L, profile, taps, renderer.base)
    assert table["shininess"] == 20.0
    for fitted, true in zip(table["leds"], truth):
        assert abs(fitted["k_d"] - true["k_d"]) < 0.02
        np.testing.assert_allclose(fitted["colour"], true["colour"], atol=0.03)
        assert abs(fitted["k_s"] - true["k_s"]) < 0.03
    assert min(report["heldout"]["change_r2"].values()) > 0.99
    assert max(report["heldout_before"]["change_r2"].values()) < 0.9

    # the Phong form of coefficients, and malformed profile constants refused
    form = phong_form(np.array([[0.6, 0.18, 0.06]]), np.array([[0.2, 0.06, 0.02]]))[0]
    assert form["k_d"] == pytest.approx(0.6) and form["k_s"] == pytest.approx(0.2)
    for bad, message in [([truth[0]], "must list 3 LEDs"), ([{"k_d": 1}] * 3, r"phong.leds\[0\] must hold"),
                         ([{**truth[0], "k_d": -1}] * 3, "finite and >= 0"),
                         ([{**truth[0], "colour": [2, 0, 0]}] * 3, r"colour must be linear RGB")]:
        with pytest.raises(ValueError, match=message):
            ProfiledRenderer(spec, ref, L, dataclasses.replace(profile, phong={**profile.phong, "leds": bad}))
