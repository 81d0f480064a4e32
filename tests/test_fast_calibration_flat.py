"""The fast path calibrated to a flat sensor's presses: LED places, the dent's spread and
per-field constants recovered blind from taps rendered with hidden ones; the profile's
composition by change; the least squares from inner products (analytic first)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from scipy import optimize

GELSIGHT = Path(__file__).resolve().parents[1] / "scenes" / "sensors" / "gelsight.toml"


def test_gram_nnls_is_nnls_from_inner_products():
    from phong_reference.calibrate import _gram_nnls

    rng = np.random.default_rng(1)
    X = rng.normal(size=(200, 6))
    y = X @ np.array([0.5, 0.0, 1.2, 0.3, 0.0, 0.7]) + rng.normal(0, 0.01, 200) - 0.4 * X[:, 1]
    np.testing.assert_allclose(_gram_nnls(X.T @ X, X.T @ y), optimize.nnls(X, y)[0], atol=1e-8)


def test_moved_leds_keep_their_azimuth():
    from phong_reference.calibrate import moved_leds
    from scenes.spec_read import load_spec

    spec = load_spec(GELSIGHT)
    moved = moved_leds(spec.leds, -0.004, 1.5)
    for a, b in zip(spec.leds, moved):
        assert b.position[2] == pytest.approx(a.position[2] - 0.004)
        assert np.arctan2(b.position[1], b.position[0]) == pytest.approx(np.arctan2(a.position[1], a.position[0]))
        assert np.hypot(*b.position[:2]) == pytest.approx(1.5 * np.hypot(*a.position[:2]))


@pytest.fixture(scope="module")
def flat(session_env):
    """The flat GelSight at 80x60, its mesh, camera and no-contact depth, and six ball
    presses (analytic) spread over the frame."""
    import trimesh

    from scenes.camera import Camera, reference_depth
    from scenes.contact import press
    from scenes.geometry import membrane_mesh
    from scenes.spec_read import load_spec

    spec = load_spec(GELSIGHT).at_resolution(80, 60)
    mesh = membrane_mesh(spec)
    camera = Camera.from_spec(spec)
    ref = reference_depth(mesh, camera)[0].astype(np.float32)
    ball = trimesh.primitives.Sphere(radius=0.002)
    pixels = [(20, 15), (60, 18), (40, 30), (25, 45), (58, 44), (45, 12), (15, 30), (66, 30)]
    depths = np.stack([press(ref, camera, mesh, ball, p, 0.0011) for p in pixels]).astype(np.float32)
    return spec, mesh, camera, ref, depths


def _profile(spec, phong=None):
    from scenes import background_model as bm
    from scenes.profile import CameraProfile, Profile

    coefficients = np.zeros((3, (bm.RADIAL_DEGREE + 1) * (2 * bm.HARMONICS + 1)))
    coefficients[:, 0] = (0.45, 0.5, 0.4)
    table = {"model": bm.MODEL, "harmonics": bm.HARMONICS, "radial_degree": bm.RADIAL_DEGREE,
             "coefficients": coefficients.tolist()}
    return Profile(sensor=spec.name, leds=tuple(led.name for led in spec.leds), camera=CameraProfile(),
                   phong={"ambient": 1.0, "background": table, **(phong or {})})


@pytest.mark.slow  # 15 to 22 s alone on 2 cores
def test_the_calibration_finds_hidden_led_places_spread_and_constants(flat):
    """Taps rendered by the fast path (linear field) with the LEDs 8 and 4 mm lower and
    farther out, the dent's spread halved and constants of its own: the calibration,
    starting from the spec's, finds every one (a candidate of its grids), and the
    held-out taps' change to rounding."""
    from phong_reference.calibrate import moved_leds
    from phong_reference.plugin import calibrate
    from phong_reference.profiled import ProfiledRenderer
    from phong_reference.bake import bake
    from phong_reference.render import light_vectors
    from scenes.captures import RealTaps

    spec, mesh, camera, ref, depths = flat
    moved = moved_leds(spec.leds[:1], -0.008, 1.5) + moved_leds(spec.leds[1:2], -0.004, 1.25) + spec.leds[2:]
    truth = [{"k_d": 0.5, "k_s": 0.0, "colour": [1.0, 0.1, 0.0]}, {"k_d": 0.3, "k_s": 0.0, "colour": [0.0, 1.0, 0.2]},
             {"k_d": 0.7, "k_s": 0.0, "colour": [0.1, 0.0, 1.0]}]
    sigma = spec.elastic.sigma_px * 0.5
    hidden = {"leds": truth, "shininess": 100.0, "positions": [list(led.position) for led in moved],
              "sigma_px": sigma, "radius_px": int(round(3 * sigma))}
    unit = _profile(spec, {"fields": {"linear": hidden}, "composition": "change"})
    renderer = ProfiledRenderer(spec, ref, light_vectors(bake(mesh, camera, moved, "linear")), unit, field="linear")
    assert np.abs(renderer.base - renderer.background).max() < 1e-6  # by change: the undeformed shading is not added
    taps = RealTaps(np.stack([renderer.render(d) for d in depths]), depths, ref, [f"t{i}" for i in range(len(depths))])
    table, report = calibrate(spec, mesh, camera, _profile(spec), taps, renderer.base, fields=("linear", "plane"))
    assert table["field"] == "linear" and table["composition"] == "change"
    found = table["fields"]["linear"]
    np.testing.assert_allclose(found["positions"], hidden["positions"], atol=1e-9)
    assert found["sigma_px"] == pytest.approx(sigma)
    for fitted, true in zip(found["leds"], truth):
        assert abs(fitted["k_d"] - true["k_d"]) < 0.02
        np.testing.assert_allclose(fitted["colour"], true["colour"], atol=0.03)
    linear = report["by_field"]["linear"]
    assert min(linear["heldout"]["change_r2"].values()) > 0.99
    assert max(linear["places"]["heldout_at_the_units_places"]["change_r2"].values()) < 0.97
    assert [m["height_mm"] for m in linear["places"]["moved"]] == [-8.0, -4.0, 0.0]

    # the profile puts the LEDs and the spread where it found them for that field only
    from phong_reference.profiled import profile_constants

    placed = profile_constants(dataclasses.replace(unit, phong={**unit.phong, "fields": {"linear": found}}), spec,
                               "linear")
    np.testing.assert_allclose([led.position for led in placed.leds], hidden["positions"], atol=1e-12)
    assert placed.elastic.sigma_px == pytest.approx(sigma)
    assert profile_constants(unit, spec, "plane").leds == spec.leds
    with pytest.raises(ValueError, match=r"positions must be 3 places \[x, y, z\] in metres"):
        profile_constants(_profile(spec, {"fields": {"linear": {**hidden, "positions": [[0, 0, 0]]}}}), spec, "linear")


def test_a_profile_with_an_unknown_composition_is_refused(flat):
    from phong_reference.profiled import composition

    spec = flat[0]
    assert composition(_profile(spec)) == "sum"
    with pytest.raises(ValueError, match=r"phong.composition must be one of \('sum', 'change'\), got 'mix'"):
        composition(_profile(spec, {"composition": "mix"}))


# --- the localisation study: analytic ---------------------------------------------------------


def rings(centres, shape=(60, 80), radius=6.0, seed=0):
    """Difference images of presses: a lit half ring per channel, each facing its own way."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[: shape[0], : shape[1]]
    out = np.zeros((len(centres), *shape, 3), np.float32)
    for i, (cu, cv) in enumerate(centres):
        r = np.hypot(u - cu, v - cv)
        ring = np.exp(-0.5 * ((r - radius) / 1.5) ** 2)
        for c, angle in enumerate((0.0, 2.1, 4.2)):
            out[i, ..., c] = 0.2 * ring * np.cos(np.arctan2(v - cv, u - cu) - angle)
    return out + rng.normal(0, 0.005, out.shape).astype(np.float32)


def test_the_correlation_filter_finds_press_centres_it_never_saw():
    from studies.sim2real.locators import CorrelationLocator

    rng = np.random.default_rng(2)
    train = rng.uniform([12, 12], [68, 48], (150, 2))
    test = rng.uniform([12, 12], [68, 48], (20, 2))
    depth = rng.uniform(0.5e-3, 1.5e-3, 150)
    model = CorrelationLocator().fit(rings(train), train, depth)
    found, _ = model.predict(rings(test, seed=1))
    assert np.median(np.linalg.norm(found - test, axis=1)) < 0.3


def test_moved_centres_follow_a_misalignment_and_a_lens():
    from scenes.spec_read import load_spec
    from scenes.camera import Camera
    from studies.sim2real.press_data import moved_centres

    camera = Camera.from_spec(load_spec(GELSIGHT).at_resolution(160, 120))
    centres = np.array([[80.0, 60.0], [40.0, 30.0], [120.0, 90.0]])
    shift = {"misalignment": {"rotation_rad": 0.0, "scale": 1.0, "du_px": 3.0, "dv_px": -2.0, "frame_share": 0.0}}
    # an output pixel p samples the simulation at p + (du, dv): what it showed at s shows at s - (du, dv)
    np.testing.assert_allclose(moved_centres(centres, shift, camera), centres - [3.0, -2.0], atol=1e-6)
    lens = {"lens_distortion": {"k1": 0.3, "k2": 0.0}}
    moved = moved_centres(centres, lens, camera)
    np.testing.assert_allclose(moved[0], centres[0], atol=0.6)  # the principal point stays
    from studies.gap.effects import source_coordinates

    coords = source_coordinates(camera.shape, camera.f, (camera.cy, camera.cx), None, lens["lens_distortion"])
    for (u, v), s in zip(moved[1:], centres[1:]):  # and the pixel found samples where the press was
        sampled = (np.interp(u, np.arange(160), coords[1][int(round(v))]), np.interp(v, np.arange(120),
                                                                                   coords[0][:, int(round(u))]))
        np.testing.assert_allclose(sampled, s, atol=0.5)
    assert moved_centres(centres, {}, camera) is not None and np.array_equal(moved_centres(centres, {}, camera),
                                                                             centres)


def test_sampled_presses_stay_in_the_fitted_box_and_range():
    from studies.sim2real.press_data import sample_presses

    centres = np.array([[30.0, 20.0], [100.0, 80.0], [60.0, 50.0]])
    depths = np.array([0.8e-3, 1.2e-3, 1.0e-3])
    c, d = sample_presses(centres, depths, 500, 0, (120, 160))
    assert c.min(axis=0).tolist() >= [26.0, 16.0] and c.max(axis=0).tolist() <= [104.0, 84.0]
    assert d.min() >= 0.8e-3 and d.max() <= 1.2e-3
    np.testing.assert_array_equal(sample_presses(centres, depths, 5, 3, (120, 160))[0],
                                  sample_presses(centres, depths, 5, 3, (120, 160))[0])
    with pytest.raises(ValueError, match=r"count must be >= 1"):
        sample_presses(centres, depths, 0, 0, (120, 160))


def test_errors_give_the_mean_offset_and_the_error_without_it():
    from studies.sim2real.press_data import Presses
    from studies.sim2real.press_scores import errors

    class Shifted:  # predicts every press 2 px right and 1 px up of its label, and its depth exactly
        def predict(self, diffs):
            return labels + [2.0, -1.0], depths

    labels = np.array([[10.0, 10.0], [20.0, 30.0], [40.0, 15.0]])
    depths = np.array([1e-3, 0.8e-3, 1.2e-3])
    blank = np.zeros((3, 8, 8, 3), np.uint8)
    out = errors(Shifted(), Presses(blank, blank, labels, depths), 1e-4)
    np.testing.assert_allclose(out["bias_px"], [2.0, -1.0])
    np.testing.assert_allclose(out["localisation_mm_median"], np.hypot(2.0, 1.0) * 0.1)
    assert out["localisation_mm_median_unbiased"] == pytest.approx(0.0, abs=1e-9)
    assert out["depth_error_mm_median_abs"] == pytest.approx(0.0)


def test_real2real_and_ring_radii_on_drawn_presses():
    from studies.sim2real.press_data import Presses
    from studies.sim2real.press_scores import appearance, real2real, ring_radii

    rng = np.random.default_rng(4)
    fit, test = rng.uniform([14, 14], [66, 46], (60, 2)), rng.uniform([14, 14], [66, 46], (12, 2))

    def presses(centres, radius, seed):
        diffs = rings(centres, radius=radius, seed=seed)
        frames = np.full(diffs.shape, 128, np.uint8)
        images = np.clip(np.rint(128 + 255 * diffs), 0, 255).astype(np.uint8)
        return Presses(images, frames, centres, np.full(len(centres), 1e-3))

    found = real2real(presses(fit, 6.0, 0), presses(test, 6.0, 1), 1e-4)
    assert found["real"]["localisation_mm_median"] < 0.03  # well under a pixel (0.1 mm)
    radii = ring_radii(presses(test, 6.0, 1), 8.0)
    assert np.all(np.abs(radii - 6.0) < 0.75)
    a = appearance(presses(test, 6.0, 1), presses(test, 4.5, 2), 8.0)
    assert a["sim_over_real"] == pytest.approx(4.5 / 6.0, abs=0.08) and a["found"] == {"real": 12, "sim": 12}


def test_offset_takes_the_fitted_presses_mean_error_off_the_centres():
    from studies.sim2real.locators import Offset
    from studies.sim2real.press_data import Presses
    from studies.sim2real.press_scores import errors

    class Shifted:  # predicts every press 2 px right and 1 px up of where its image puts it
        def predict(self, diffs):
            return np.rint(diffs[:, 0, 0, :2] * 255.0) + [2.0, -1.0], np.full(len(diffs), 1e-3)

    def presses(centres):
        images = np.zeros((len(centres), 4, 4, 3), np.uint8)
        images[:, 0, 0, :2] = centres  # the model reads where the "image" puts the press off its first pixel
        return Presses(images, np.zeros_like(images), np.asarray(centres, np.float64), np.full(len(centres), 1e-3))

    fit, test = presses([[10, 10], [20, 30], [40, 15]]), presses([[50, 60], [70, 20]])
    model = Offset.fitted(Shifted(), fit)
    np.testing.assert_allclose(model.offset_px, [2.0, -1.0])
    assert errors(model, test, 1e-4)["localisation_mm_median"] == pytest.approx(0.0, abs=1e-9)
    assert errors(Offset(Shifted()), test, 1e-4)["localisation_mm_median"] == pytest.approx(np.hypot(2, 1) * 0.1)
    np.testing.assert_allclose(model.predict(test.differences())[1], 1e-3)  # the depth is the model's own


# --- the environment's terms (phong_reference.environment) ------------------------------------


def test_the_environment_s_terms_from_normals_displacement_and_light():
    from phong_reference import environment as env

    up = np.zeros((3, 2, 2), np.float32)
    up[2] = -1.0  # facing the camera
    np.testing.assert_allclose(env.harmonics(up)[:, 0, 0], [0, 0, -1, 0, 0, 0, 0, 2])
    tilted = up.copy()
    tilted[0], tilted[2] = 0.6, -0.8
    u = np.array([[0.0, 1e-3], [2e-3, 0.0]], np.float32)
    lit = np.full((3, 2, 2), 0.5, np.float32)
    T = env.terms(tilted, up, u, lit)
    assert T.shape == (len(env.TERMS), 3, 2, 2)
    np.testing.assert_allclose(T[0], 0.6)  # x
    np.testing.assert_allclose(T[2], 0.2)  # z: -0.8 - (-1)
    np.testing.assert_allclose(T[7], 3 * 0.64 - 3 * 1.0)  # 3z^2 - 1
    np.testing.assert_allclose(T[8], 0.3)  # x, lit by half
    np.testing.assert_allclose(T[16][0], [[0.0, 1.0], [2.0, 0.0]])  # the thinning in mm
    np.testing.assert_allclose(T[17][1], [[0.0, 0.5], [1.0, 0.0]])
    assert not env.terms(up, up, np.zeros((2, 2)), lit).any()
    c = np.zeros((len(env.TERMS), 3), np.float32)
    c[16] = (0.01, -0.02, 0.03)
    np.testing.assert_allclose(env.change(c, T)[:, 1, 0], [0.02, -0.04, 0.06], rtol=1e-6)
    assert env.coefficients(None) is None
    np.testing.assert_allclose(env.coefficients(env.entry(c)), c)
    for bad in ({"terms": ["x"], "coefficients": [[0, 0, 0]]}, {"coefficients": c.tolist()},
                {"terms": list(env.TERMS), "coefficients": np.full((18, 3), np.nan).tolist()}):
        with pytest.raises(ValueError, match="phong.environment must"):
            env.coefficients(bad)


def _hidden_environment():
    from phong_reference import environment as env

    c = np.zeros((len(env.TERMS), 3))
    c[env.TERMS.index("z")] = (0.05, 0.0, -0.08)
    c[env.TERMS.index("xx-yy lit")] = (0.0, 0.1, 0.0)
    c[env.TERMS.index("thinning")] = (-0.01, -0.02, 0.04)
    return c


def test_a_profile_s_environment_is_rendered_as_its_terms(flat):
    """LEDs dark, the thinning alone: the change is its coefficient times the surface's
    displacement in mm, channel by channel."""
    from phong_reference import environment as env
    from phong_reference.bake import bake
    from phong_reference.profiled import ProfiledRenderer
    from phong_reference.render import light_vectors

    spec, mesh, camera, ref, depths = flat
    c = np.zeros((len(env.TERMS), 3))
    c[env.TERMS.index("thinning")] = (0.01, -0.02, 0.03)
    dark = [{"k_d": 0.0, "k_s": 0.0, "colour": [0.0, 0.0, 0.0]} for _ in spec.leds]
    unit = _profile(spec, {"leds": dark, "shininess": 10.0, "composition": "change", "environment": env.entry(c)})
    renderer = ProfiledRenderer(spec, ref, light_vectors(bake(mesh, camera, spec.leds, "linear")), unit)
    u_mm = (ref - renderer._membrane.deformed(depths[2])) * 1e3
    assert u_mm.max() > 0.5
    change = renderer.render(depths[2]) - renderer.base
    inside = camera.mask
    for ch in range(3):
        np.testing.assert_allclose(change[..., ch][inside], c[16, ch] * u_mm[inside], atol=2e-6)
    # without the entry, the same dark profile does not change at all
    plain = ProfiledRenderer(spec, ref, light_vectors(bake(mesh, camera, spec.leds, "linear")),
                             _profile(spec, {"leds": dark, "shininess": 10.0, "composition": "change"}))
    assert np.abs(plain.render(depths[2]) - plain.base).max() < 1e-6


def test_the_calibration_finds_a_hidden_environment(flat):
    """Taps whose change holds, beside the LEDs', an environment of three terms (an
    order-1 and an order-2 harmonic and the thinning): fitted with the environment the
    held-out taps' change is recovered; with the LEDs alone it is not."""
    from phong_reference import environment as env
    from phong_reference.bake import bake
    from phong_reference.calibrate import fit_led_constants
    from phong_reference.profiled import ProfiledRenderer
    from phong_reference.render import light_vectors
    from scenes.captures import RealTaps

    spec, mesh, camera, ref, depths = flat
    truth = [{"k_d": 0.5, "k_s": 0.0, "colour": [1.0, 0.1, 0.0]}, {"k_d": 0.3, "k_s": 0.0, "colour": [0.0, 1.0, 0.2]},
             {"k_d": 0.7, "k_s": 0.0, "colour": [0.1, 0.0, 1.0]}]
    L = light_vectors(bake(mesh, camera, spec.leds, "linear"))
    hidden = _profile(spec, {"leds": truth, "shininess": 20.0, "composition": "change",
                             "environment": env.entry(_hidden_environment())})
    renderer = ProfiledRenderer(spec, ref, L, hidden)
    taps = RealTaps(np.stack([renderer.render(d) for d in depths]), depths, ref, [f"t{i}" for i in range(len(depths))])
    start = _profile(spec)  # as calibrate_fast starts: composed by sum, nothing calibrated
    table, report = fit_led_constants(spec, camera, ref, L, start, taps, renderer.base)
    assert min(report["heldout"]["change_r2"].values()) > 0.995
    assert table["environment"]["terms"] == list(env.TERMS)
    _, alone = fit_led_constants(spec, camera, ref, L, start, taps, renderer.base, with_environment=False)
    assert min(alone["heldout"]["change_r2"].values()) < 0.98
    assert "environment" not in alone
