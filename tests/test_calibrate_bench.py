"""The calibration's blind benchmark (pbr_tactile.calibrate_bench): what it hides and how
it scores, analytically (its rendered runs are `tactile-sim calibrate benchmark`)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from pbr_tactile import calibrate_bench as cb
from pbr_tactile import image_fit as imf
from pbr_tactile import image_model as im
from pbr_tactile.basis import BASIS_EFFECTS, basis_layout
from pbr_tactile.effects import Effects
from scenes.camera import Camera
from scenes.spec_read import default_spec, load_spec
from tests.fake_basis import each_variant_traced

SPEC_2023 = "scenes/sensors/geltip_2023.toml"
GRID = {"absorption_per_m": (5.0, 80.0), "scattering_per_m": (10.0, 250.0)}


def _azimuth(led) -> float:
    return math.atan2(led.position[1], led.position[0])


def test_draws_stay_in_their_ranges_and_hide_spans_and_the_lens():
    spec = load_spec(SPEC_2023)
    camera = Camera.from_spec(spec)
    _, _, spans, _, _ = basis_layout(spec)
    edge = camera.mask_radius_px / camera.f
    lo, hi = cb.RANGES["lens_edge_shift"]
    shares, shifts = [], []
    for seed in range(40):
        nl, gains, effects = cb.draw(np.random.default_rng(seed), len(spans), GRID, spans, edge, camera.k1)
        assert len(nl.span_rad) == len(spans) == 3 and gains.shape == (3, 3)
        shares += [s / t for s, t in zip(nl.span_rad, spans)]
        shifts.append((nl.k1 - camera.k1) * edge**2)
        assert all(effects[k] in GRID[k] for k in GRID)
    assert cb.RANGES["span_share"][0] <= min(shares) and max(shares) <= cb.RANGES["span_share"][1]
    assert lo <= min(shifts) and max(shifts) <= hi
    # drawn, not fixed: both signs of the lens and spans either side of the spec's
    assert min(shifts) < 0 < max(shifts) and min(shares) < 1 < max(shares)
    # a spec without groups draws no spans
    nl, _, _ = cb.draw(np.random.default_rng(0), 3, GRID)
    assert nl.span_rad == ()


def test_the_virtual_build_puts_each_led_where_the_hidden_values_say():
    spec = load_spec(SPEC_2023)
    nl = im.Nonlinear(0.2, (0.1, -0.05, 0.12), (0.2, 0.3, 0.4), 1.0, (0.0, 0.0), (-0.3, 0.0), 2.0,
                      span_rad=(1.8, 2.3, 2.0))
    build, share, unit = cb.virtual_build(spec, nl)
    assert len(build.leds) == 18 and share == pytest.approx(3 / 18)
    for g, group in enumerate(spec.led_groups):
        leds = [led for led, m in zip(build.leds, unit) if m == g]
        assert len(leds) == group.count
        want = group.arc_centre_rad + nl.led_azimuth_rad[g] + nl.span_rad[g] * group.offsets()
        got = [_azimuth(led) for led in leds]
        assert np.allclose(np.remainder(np.subtract(got, want) + math.pi, 2 * math.pi) - math.pi, 0.0, atol=1e-12)
    # single LEDs are turned by their own azimuth, their build unchanged otherwise
    plain = default_spec()
    build, share, unit = cb.virtual_build(plain, nl)
    assert share == 1.0 and list(unit) == [0, 1, 2]
    for led, old, a in zip(build.leds, plain.leds, nl.led_azimuth_rad):
        assert math.remainder(_azimuth(led) - _azimuth(old) - a, 2 * math.pi) == pytest.approx(0.0, abs=1e-12)
        assert led.position[2] == old.position[2] and led.colour == old.colour


def test_benchmark_scoring_forgives_only_the_led_renaming():
    camera = Camera.from_spec(default_spec())
    truth = im.Nonlinear(0.3, (0.01, -0.02, 0.03), (0.2, 0.4, 0.0), 1.02, (3.0, -2.0), (-0.3, 0.0), 2.0)
    gains = np.array([[0.9, 0.2, 0.3], [0.1, 0.8, 0.2], [0.3, 0.3, 0.7]])
    effects = {"absorption_per_m": 20.0}
    k = 1  # the fit turned by one LED spacing: its LED j is the true LED j + 1
    perm = [(j + k) % 3 for j in range(3)]
    fit = {"rotation_rad": truth.tied().rotation_rad + 2 * math.pi / 3, "gamma": 2.0, "scale": 1.02, "shift_px": [3.0, -2.0],
           "vignetting": [-0.3, 0.0], "led_leak": [truth.leak[p] for p in perm],
           "led_gains": gains[perm] * 5.0, "effects": effects, "k1": 0.0}
    errors, reported = cb._errors(fit, truth, gains, effects, 3, camera)
    assert max(errors.values()) < 1e-9 and max(reported.values()) < 1e-9
    fit["led_gains"] = gains * 5.0  # not renamed: the gains no longer match
    assert max(cb._errors(fit, truth, gains, effects, 3, camera)[0].values()) > 0.5


def test_spans_and_the_lens_are_scored():
    camera = Camera.from_spec(load_spec(SPEC_2023))
    truth = im.Nonlinear(0.3, (0.0, 0.0, 0.0), (0.2, 0.4, 0.3), 1.0, (0.0, 0.0), (-0.3, 0.0), 2.0,
                         span_rad=(2.0, 2.2, 1.9), k1=0.02)
    gains = np.array([[0.9, 0.2, 0.3], [0.1, 0.8, 0.2], [0.3, 0.3, 0.7]])
    fit = {"rotation_rad": truth.rotation_rad, "gamma": 2.0, "scale": 1.0, "shift_px": [0.0, 0.0],
           "vignetting": [-0.3, 0.0], "led_leak": list(truth.leak), "led_gains": gains, "k1": 0.02,
           "arc_span_rad": list(truth.span_rad), "effects": {}}
    scored, reported = cb._errors(fit, truth, gains, {}, 3, camera)
    # (a distorted lens is inverted through a table: 1e-7 of the shift's range)
    assert max(scored.values()) < 1e-6 and max(reported.values()) < 1e-9
    wrong = {**fit, "arc_span_rad": [2.0, 2.2 * 1.2, 1.9]}
    assert cb._errors(wrong, truth, gains, {}, 3, camera)[0]["led1_span"] == pytest.approx(0.2)
    # scale and k1 trade against each other: the lens is scored by where it puts the rays
    # (against the shift's range), each of the two is reported only
    edge = camera.mask_radius_px / camera.f
    half = (cb.RANGES["lens_edge_shift"][1] - cb.RANGES["lens_edge_shift"][0]) / 2
    off = {**fit, "k1": 0.02 + 0.05 / edge**2}
    scored, reported = cb._errors(off, truth, gains, {}, 3, camera)
    assert reported["lens_edge_shift"] == pytest.approx(0.05 / half)
    assert scored["lens_mapping_px"] > 0.1 and "scale" not in scored and "lens_edge_shift" not in scored
    # a lens that moves every ray outwards by 2 % at the edge moves them about 1.4 % RMS
    wider = cb.lens_error_px(camera, dataclasses.replace(truth, k1=0.0), 1.02, 0.0)
    r = np.sqrt(0.5) * camera.mask_radius_px
    assert wider == pytest.approx(0.02 * r, rel=0.1)

def _formula_basis(spec, mesh, camera, effects, film, *args, depth=None, **kwargs):
    """A stand-in for the reference's per-source render, from formulas: each LED lights a
    lobe round its own azimuth, brighter towards the rim, its leak a ring; both drawn by
    each ray's angle off the axis, so a wider camera sees them smaller."""
    from pbr_tactile.scene import led_sources

    w, h = film
    small = camera.scaled(w, h)
    v, u = np.mgrid[0:h, 0:w].astype(float)
    theta = np.arctan(np.hypot(u - small.cx, v - small.cy) / small.f)
    phi = np.arctan2(v - small.cy, u - small.cx)
    t = theta / math.radians(60.0)
    images = []
    for src in led_sources(spec, effects):
        led = spec.leds[int(src["name"][3:].split("_")[0])]
        a = _azimuth(led)
        if src["name"].endswith("_leak"):
            images.append(np.exp(-((t - 0.5) / 0.25) ** 2) * (1.2 + np.cos(phi - a)))
        else:
            images.append((0.05 + t**2) * np.exp(4.0 * (np.cos(phi - a) - 1.0)))
    mean = np.stack(images, -1)
    return {"mean": mean, "variance": np.full(mean.shape, 1e-8), "names": np.array([s["name"] for s in led_sources(
        spec, effects)]), "response": np.ones((mean.shape[-1], 3))}


def _formula_model(film=(40, 30)) -> im.ImageModel:
    """The image model of the default sensor's formula basis (``_formula_basis``), its lens fitted."""
    spec = default_spec()
    camera = Camera.from_spec(spec)
    effects = Effects().with_settings([f"{k}={v}" for k, v in BASIS_EFFECTS.items()])
    basis = _formula_basis(spec, None, camera, effects, film)
    return im.ImageModel(basis["mean"], basis["names"], camera, (camera.cx, camera.cy, camera.mask_radius_px),
                         lens=True)


@pytest.mark.slow
def test_a_group_sensor_drawn_led_by_led_is_recovered_through_the_whole_benchmark(monkeypatch):
    """The benchmark's loop end to end on the real unit's spec, with the render replaced by
    formulas that depend on where each LED sits: the virtual sensor drawn with all 18 LEDs
    along its hidden arcs, seen through its hidden lens and summed per group, and the
    calibration's model with one render per group turned along the arc, meet, so the
    hidden spans, turns and lens come back."""
    from pbr_tactile import calibrate as cal

    monkeypatch.setattr(cb, "emitter_basis", _formula_basis)
    monkeypatch.setattr(cal, "emitter_basis", each_variant_traced(_formula_basis))
    spec = load_spec(SPEC_2023)
    camera = Camera.from_spec(spec)
    grid = {"absorption_per_m": (5.0,), "scattering_per_m": (250.0,)}
    result = cb.benchmark(spec, None, camera, cases=1, seed=3, film=(80, 60), grid=grid)
    case = result["per_case"][0]
    errors = case["errors"]
    assert {"led0_span", "led1_span", "led2_span", "lens_mapping_px"} <= set(errors)
    assert case["hidden"]["k1"] != camera.k1 and len(case["hidden"]["span_rad"]) == 3
    assert max(errors[f"led{m}_span"] for m in range(3)) < 0.1, errors
    # the lens' mapping to within half a film pixel (8 camera pixels at 80 x 60)
    assert errors["lens_mapping_px"] * 15.0 < 4.0 and errors["rotation_rad"] < 0.05, errors
    assert result["median_relative_error"] < 0.05
    # its Monte Carlo error is stated per parameter (the formulas' noise is tiny)
    assert case["mc_error"]["gamma"] < 0.01 and not case["beyond_tolerance"]


def test_the_search_descends_from_every_start_before_it_keeps_the_best():
    """A blind sensor's image whose starts' own losses rank a wrong basin first: kept by
    them (screen=0), the search stopped short of the truth; a few steps from every start
    first, it reaches it. The image is the model's own (no noise), so the truth's loss is 0."""
    model = _formula_model()
    truth = im.Nonlinear(0.229, (-0.141, 0.066, -0.145), (0.455, 0.308, 0.557), 0.913, (10.24, -13.0), (-0.426, 0.0),
                         2.03, k1=0.093)
    gains = np.array([[0.65, 0.41, 0.39], [0.91, 0.38, 0.3], [0.43, 0.67, 0.64]])
    gains = gains / np.percentile(model.design(truth)[model.inside].sum(axis=1), 95)
    real = model.render(truth, gains, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
    fitter = imf.ImageFitter(model, real, model.inside)
    kept_by_start = fitter.search(screen=0)
    fit = fitter.search()
    assert kept_by_start.loss > 1e-7
    assert fit.loss < 1e-10 and fit.converged
    assert abs(fit.nl.gamma - truth.gamma) < 1e-3 and abs(fit.nl.scale - truth.scale) < 1e-3


def test_the_fits_covariance_predicts_how_refits_scatter_under_noise():
    """Noise of a known variance on the model's own image, drawn again and again: the
    spread of the refitted shift and tied rotation matches the standard errors the
    covariance predicts, and no refitted value spreads much wider than predicted (the
    response exponent spread 0.6 of its prediction over 40 draws: its direction is flat,
    where the first-order covariance is conservative and refits stop early)."""
    model = _formula_model()
    truth = im.Nonlinear(0.3, (0.0, 0.0, 0.0), (0.3, 0.4, 0.2), 1.0, (2.0, -3.0), (-0.4, 0.0), 2.0, k1=0.02)
    gains = np.array([[0.65, 0.41, 0.39], [0.91, 0.38, 0.3], [0.43, 0.67, 0.64]])
    gains = gains / np.percentile(model.design(truth)[model.inside].sum(axis=1), 95)
    clean = model.render(truth, gains, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
    sigma = 0.01
    variance = np.full(clean.shape, sigma**2)
    predicted = imf.tied_errors(truth, imf.ImageFitter(model, clean, model.inside).covariance(truth, variance))
    rng = np.random.default_rng(1)
    fits = [imf.ImageFitter(model, clean + rng.normal(0.0, sigma, clean.shape), model.inside).fit(truth, 300).nl
            for _ in range(12)]
    for name, values in (("shift_u", [f.shift_px[0] for f in fits]),
                         ("rotation_rad", [f.tied().rotation_rad for f in fits])):
        ratio = np.std(values, ddof=1) / predicted[name]
        assert 0.7 < ratio < 1.5, (name, ratio)
    assert np.std([f.gamma for f in fits], ddof=1) < 1.5 * predicted["gamma"]
    assert "led_azimuth_rad[0]" not in predicted and predicted["gamma"] > 0


def test_the_covariance_refuses_a_fit_with_taps():
    model = _formula_model()
    image = np.zeros((model.h, model.w, 3))
    view = imf.TapView(np.zeros((model.h, model.w, model.S)), image, model.inside)
    fitter = imf.ImageFitter(model, image, model.inside, taps=[view])
    with pytest.raises(ValueError, match="with taps is not covered"):
        fitter.covariance(im.Nonlinear.start(3), np.ones(image.shape))
