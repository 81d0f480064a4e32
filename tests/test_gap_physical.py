"""The diagnosis when the reference rendered the simulation: its candidates are the
reference's own switches (studies.gap.physical, studies.gap.reference_model).

The per-source renders are replaced here by an analytic stand-in for
``pbr_tactile.basis.emitter_basis`` (each LED's light falls off as exp(-sigma_a d)
from its place on the image, its leak into the core lights a ring, a contact brightens
where it presses), so that the chain (per-source weights, spectra, grid interpolation,
fits, report) is checked exactly and in seconds; the blind benchmark on the reference
itself is ``tactile-sim diagnose benchmark --physical``.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import trimesh

from pbr_tactile.effects import Effects
from scenes.camera import Camera, reference_depth
from scenes.contact import press
from scenes.geometry import membrane_mesh
from studies.gap import reference_model, smoothing, source_basis
from studies.gap.diagnosis import Diagnosis
from studies.gap.pairs import Pairs, split
from studies.gap.physical import physical_catalogue
from studies.gap.reference_model import ReferenceModel
from studies.gap.source_basis import SourceBasis

FILM = (80, 60)


def _gain() -> float:
    """An exposure that puts the stand-in's brightest LED light near 0.5."""
    from pbr_tactile.render import source_response
    from pbr_tactile.scene import led_sources
    from scenes.spec_read import default_spec

    effects = Effects(core_light_leak=0.0)
    return 0.5 / (50.0 * float(source_response(led_sources(default_spec(), effects), effects).max()))


GAIN = _gain()
PIXELS = [(320, 240), (250, 200), (400, 300), (200, 330), (460, 180), (150, 240), (320, 90), (320, 400)]


def fake_basis(spec, mesh, camera, effects, film, photons=0, spp=0, passes=0, seed=0, use_cache=True, depth=None,
               ref_depth=None, solids=None, no_contact_runs=0, inscatter="fluence", perturb=None, only=None):
    """Per-source images with a known physics: LED m's light exp(-sigma_a d_m) (d_m the
    distance in metres over the image from the LED's place), its leak a ring at 0.4 of
    the image radius on the LED's side (nearer the centre, the tip, the narrower its cone up
    the tube), a contact adding its indentation's shading. With ``perturb`` ((K, 3) rows of
    absorption, scattering, paint albedo), each row's images too, as the re-weighting
    returns them (``ESS``: each row's effective-sample-size ratio, 1 by default). With
    ``only``, those sources' columns."""
    if only is not None:
        out = fake_basis(spec, mesh, camera, effects, film, depth=depth, ref_depth=ref_depth)
        return {k: (out[k][..., list(only)] if k != "names" else out[k][list(only)]) for k in out}
    if perturb is not None:
        from pbr_tactile.reweight import PARAMETERS, valid

        out = fake_basis(spec, mesh, camera, effects, film, depth=depth, ref_depth=ref_depth)
        rows = [fake_basis(spec, mesh, camera, dataclasses.replace(effects, **dict(zip(PARAMETERS, map(float, row)))),
                           film, depth=depth, ref_depth=ref_depth) for row in np.asarray(perturb)]
        ess = np.array([[ESS.get(tuple(float(v) for v in row), 1.0)] * out["mean"].shape[-1] for row in perturb])
        return {**out, "perturb": np.asarray(perturb), "variant_mean": np.stack([r["mean"] for r in rows]),
                "variant_variance": np.stack([r["variance"] for r in rows]), "ess_ratio": ess, "valid": valid(ess)}
    w, h = film
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    x, y = (u - w / 2) / (h / 2), (v - h / 2) / (h / 2)
    rho = np.hypot(x, y)
    dent = 0.0
    if depth is not None:
        from skimage.transform import resize

        dent = resize(np.asarray(ref_depth - depth, np.float64), (h, w), order=1, anti_aliasing=True) / 1e-3
    images, names = [], []
    for m in range(len(spec.leds)):
        a = 2 * np.pi * m / len(spec.leds)
        d = 0.01 * np.hypot(x - np.cos(a), y - np.sin(a))  # metres
        images.append(50.0 * np.exp(-effects.absorption_per_m * d) * (1 + 0.8 * dent * (1 + np.cos(np.arctan2(y, x) - a))))
        names.append(f"led{m}")
        if effects.core_light_leak > 0:
            ring = 0.4 * (1.0 - effects.core_leak_cone_rad)
            images.append(80.0 * np.exp(-((rho - ring) / 0.12) ** 2) * (1 + np.cos(np.arctan2(y, x) - a)) + 5 * dent)
            names.append(f"led{m}_leak")
    mean = np.stack(images, axis=-1).astype(np.float32)
    # the renders' Monte Carlo noise: NOISE of each image, per pixel
    return {"mean": mean, "variance": (NOISE * mean) ** 2, "names": np.array(names)}


#: The stand-in basis' relative standard error per pixel (``fake_basis``'s variance).
NOISE = 0.01
#: The stand-in re-weighting's ESS ratio of a row (absorption, scattering, albedo), 1 where not listed.
ESS: dict = {}


@pytest.fixture
def stub(monkeypatch):
    import pbr_tactile.basis

    monkeypatch.setattr(pbr_tactile.basis, "emitter_basis", fake_basis)


@pytest.fixture(scope="module")
def scene(spec):
    mesh = membrane_mesh(spec)
    camera = Camera.from_spec(spec)
    ref = reference_depth(mesh, camera)[0].astype(np.float32)
    shapes = [trimesh.primitives.Sphere(radius=0.004), trimesh.creation.cylinder(radius=0.003, height=0.01)]
    depth = np.stack([press(ref, camera, mesh, shapes[i % 2], p, 0.0015) for i, p in enumerate(PIXELS)])
    return camera, ref, depth.astype(np.float32)


def renderer(**effects) -> dict:
    return {"renderer": "pbr", "estimator": "photons", "exposure_gain": GAIN,
            "effects": dataclasses.asdict(Effects(**effects))}


def rendered(spec, scene, params: dict, **effects) -> np.ndarray:
    """(N, H, W, 3) full-resolution images of the stand-in with ``params`` (a reference
    model's candidates) over a simulation with ``effects``."""
    camera, ref, depth = scene
    model = ReferenceModel(spec, renderer(**effects), 1, SourceBasis(spec, renderer(**effects), depth, film=FILM))
    return np.stack([model._resized(model.image(i, params)) for i in range(len(depth))])


def test_every_field_of_effects_is_a_candidate_and_new_ones_join(spec):
    catalogue, kinds, grids = physical_catalogue(spec, Effects())
    for f in dataclasses.fields(Effects):
        assert f.name in catalogue
    assert kinds["core_light_leak"] == "linear" and kinds["absorption_per_m"] == "render"
    assert kinds["sensor_noise"] == "unpredictable" and kinds["alignment"] == "fast"
    assert 20.0 in grids["absorption_per_m"]["values"]  # the simulation's own value is a grid point

    @dataclasses.dataclass(frozen=True)
    class More(Effects):
        membrane_haze: float = 2.0

    catalogue, kinds, grids = physical_catalogue(spec, More())
    assert kinds["membrane_haze"] == "render" and grids["membrane_haze"]["values"] == (0.5, 2.0, 8.0)


def test_powers_leak_and_spectra_are_linear_in_the_sources(spec, scene, stub):
    camera, ref, depth = scene
    model = ReferenceModel(spec, renderer(), 1, SourceBasis(spec, renderer(), depth, film=FILM))
    raw = model.basis.images(0)
    B = model.sources(0, {})  # the LEDs' own images as rendered, their leaks' smoothed
    leak = np.array([n.endswith("_leak") for n in model.basis.names])
    assert np.array_equal(B[..., ~leak], raw[..., ~leak]) and not np.allclose(B[..., leak], raw[..., leak])
    assert np.allclose(B[..., leak].sum((0, 1)), raw[..., leak].sum((0, 1)), rtol=0.02)  # light kept
    R = model.responses((0.0,) * len(spec.leds), 1.0, 1.0)
    names = model.basis.names
    expect = GAIN * sum(0.5 * (2.0 if n.startswith("led1") else 1.0) * B[..., s, None] * R[int(n[3])]
                        for s, n in enumerate(names))
    params = {"core_light_leak": {"fraction": 0.5},
              "led_power": {f"power_{m}": 2.0 if m == 1 else 1.0 for m in range(len(spec.leds))}}
    # The capture is exposed from its own no-contact frame (pbr_tactile.plugin's rule).
    mask = camera.scaled(*FILM).mask
    nc = model.sources(source_basis.NO_CONTACT, {})
    level = np.percentile((GAIN * sum(0.5 * (2.0 if n.startswith("led1") else 1.0) * nc[..., s, None] * R[int(n[3])]
                                      for s, n in enumerate(names)))[mask], 99.5)
    level0 = np.percentile((GAIN * sum(nc[..., s, None] * R[int(n[3])] for s, n in enumerate(names)
                                       if not n.endswith("_leak")))[mask], 99.5)
    assert np.allclose(model.image(0, params), np.clip(expect * level0 / level, 0, 1), atol=1e-6)
    # So every LED twice as bright is the same image.
    brighter = {"led_power": {f"power_{m}": 2.0 for m in range(len(spec.leds))}}
    assert np.allclose(model.image(0, brighter), model.image(0, {}), atol=1e-6)
    # At the identity (no leak) only the LEDs' own images count.
    plain = GAIN * sum(B[..., s, None] * R[int(n[3])] for s, n in enumerate(names) if not n.endswith("_leak"))
    assert np.allclose(model.image(0, {}), np.clip(plain, 0, 1), atol=1e-6)
    # A peak shift moves each LED's colour through the camera's bands.
    shifted = model.responses((15.0,) + (0.0,) * (len(spec.leds) - 1), 1.0, 1.0)
    assert not np.allclose(shifted[0], R[0]) and np.allclose(shifted[1:], R[1:])


@pytest.mark.parametrize("params", [{"camera_response": {"on": 0.0}}, {"led_spectra": {"on": 0.0}},
                                    {"led_power": {"power_0": 1.6, "power_1": 1.0, "power_2": 0.7}}])
def test_a_change_of_the_lights_colours_acts_on_the_simulated_image_as_a_matrix(spec, scene, stub, params):
    """With the LEDs' responses invertible, a colour change is a 3x3 matrix on the
    simulated image itself: exact, and free of the basis' noise (here: none)."""
    camera, ref, depth = scene
    model = ReferenceModel(spec, renderer(), 8, SourceBasis(spec, renderer(), depth, film=FILM))  # at the film
    params = {name: {**model.catalogue[name].identity, **p} for name, p in params.items()}
    A = model.colour_matrix(params)
    assert A is not None and not np.allclose(A / A[0, 0], np.eye(3))
    keys = list(range(len(depth)))
    sim = np.stack([model.image(i, {}) for i in keys])
    real = np.stack([model.image(i, params) for i in keys])
    rng = np.random.default_rng(0)  # the taps' basis images now noisy: the prediction does not read them
    for i in keys:
        model.basis._images[(i, None, None)] = model.basis._images[(i, None, None)] * np.float32(
            1 + 0.2 * rng.standard_normal(model.basis._images[(i, None, None)].shape))
    model._rendered.clear()
    pred = model.predict(sim, depth, params, keys=keys)
    seen = sim.max(axis=-1) < 0.98  # a saturated simulated pixel has lost its colour
    assert seen.mean() > 0.5
    assert np.abs(pred - real)[seen].max() < 2e-3 and np.abs(sim - real)[seen].max() > 0.05
    # A switch half-way is half-way in colour, not mostly at one end (blended at one total).
    name = next(iter(params))
    if name != "led_power":
        half = model.predict(sim, depth, {name: {**params[name], "on": 0.5}}, keys=keys)
        assert 0.25 < np.abs(half - sim).mean() / np.abs(pred - sim).mean() < 0.75


def test_a_re_rendered_effect_is_interpolated_between_grid_points(spec, scene, stub):
    """Absorption acts as exp(-sigma_a d): the geometric interpolation is exact between grid
    points (the leaks' images, which it leaves alone, smoothed as every one is)."""
    camera, ref, depth = scene
    model = ReferenceModel(spec, renderer(), 1, SourceBasis(spec, renderer(), depth, film=FILM))
    got = model.interpolated(2, "absorption_per_m", 50.0)
    truth = fake_basis(spec, None, camera, dataclasses.replace(Effects(), absorption_per_m=50.0,
                                                               core_light_leak=source_basis.LEAK_BASIS),
                       FILM, depth=depth[2], ref_depth=ref)["mean"]
    leak = np.array([n.endswith("_leak") for n in model.basis.names])
    film = camera.scaled(*FILM)
    truth[..., leak] = smoothing.axially_smoothed(truth[..., leak], (film.cx, film.cy), smoothing.LEAK_SMOOTH_PX)
    assert np.allclose(got, truth, rtol=1e-4, atol=1e-4)
    # The grid points (50, 120) are re-weighted from the identity's render: none of their own.
    assert "absorption_per_m" not in model.basis.cost and model.basis.cost["identity"]["renders"] == 1


def test_a_grid_point_of_no_weight_is_not_rendered(spec, scene, stub):
    """A re-rendered candidate at a grid point reads that point alone: a fit at the
    identity renders nothing of its own, one at an inner point renders no neighbour (on
    the 36-pair bench the leak's cone, fitted at 0, rendered 0.3 on every held-out tap)."""
    camera, ref, depth = scene
    model = ReferenceModel(spec, renderer(), 1, SourceBasis(spec, renderer(), depth, film=FILM))
    assert model.grids["absorption_per_m"]["values"] == (5.0, 10.0, 20.0, 50.0, 120.0)
    np.testing.assert_array_equal(model.interpolated(0, "membrane_compliance", 1.0), model.rendered(0))
    assert "membrane_compliance" not in model.basis.cost
    at = model.interpolated(0, "membrane_compliance", 0.6)
    np.testing.assert_array_equal(at, model.rendered(0, "membrane_compliance", 0.6))
    assert model.basis.cost["membrane_compliance"]["renders"] == 1  # 1.0 is the identity
    # a re-weighted candidate at an inner grid point reads it alone (not 20 or 5)
    np.testing.assert_array_equal(model.interpolated(0, "absorption_per_m", 10.0),
                                  model.rendered(0, "absorption_per_m", 10.0))
    between = model.interpolated(0, "membrane_compliance", 1.1)
    assert model.basis.cost["membrane_compliance"]["renders"] == 2
    t = (1.1 - 1.0) / (1.25 - 1.0)
    np.testing.assert_allclose(between, (1 - t) * model.rendered(0) + t * model.rendered(0, "membrane_compliance", 1.25),
                               rtol=1e-5)


def test_a_re_rendered_change_is_smoothed_as_a_ratio():
    """A change that scales the light smoothly passes whole; the renders' noise is cut."""
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:60, 0:80]
    base = np.stack([1.0 + ((xx // 10 + yy // 10) % 2), np.exp(-xx / 40.0)], axis=-1).astype(np.float32)
    ratio = (0.5 + 0.4 * np.sin(xx / 25.0))[..., None].astype(np.float32)
    # An exact ratio away from the film's edges (the filter's nearest-edge padding aside).
    inner = (slice(8, -8), slice(8, -8))
    truth = (base * ratio - base)[inner]
    assert np.abs(smoothing.smoothed_change(base * ratio, base)[inner] - truth).max() < 0.02 * np.abs(truth).max()
    noisy = base * ratio * (1 + 0.1 * rng.standard_normal(base.shape)).astype(np.float32)
    plain = np.abs((noisy - base) - (base * ratio - base))[inner].mean()
    smoothed = np.abs(smoothing.smoothed_change(noisy, base) - (base * ratio - base))[inner].mean()
    assert smoothed < plain / 3


def test_a_leak_image_is_smoothed_around_the_tubes_axis_more_than_along_it():
    """Around each circle about the centre a Gaussian of sigma px of arc: an azimuthal
    cosine at radius r keeps exp(-(sigma / r)^2 / 2) of itself; a glow that depends on the
    radius alone keeps its profile (a ring 3 px wide), a constant is exact, and noise is cut."""
    h, w = 60, 80
    v, u = np.mgrid[0:h, 0:w]
    cx, cy = 39.5, 29.5
    r, azimuth = np.hypot(u - cx, v - cy), np.arctan2(v - cy, u - cx)
    ring = np.exp(-(((r - 12) / 3) ** 2))
    images = np.stack([ring, np.cos(azimuth), np.ones((h, w))], axis=-1).astype(np.float32)
    out = smoothing.axially_smoothed(images, (cx, cy), (4.0, 0.0))
    assert np.abs(out[..., 2] - 1).max() < 1e-6
    assert np.abs(out[..., 0] - ring).max() < 0.03
    band = (r > 15) & (r < 25)
    kept = np.exp(-0.5 * (4.0 / r[band]) ** 2)
    assert np.abs(out[..., 1][band] - kept * images[..., 1][band]).max() < 0.01
    assert np.abs(out[..., 1][band] - images[..., 1][band]).max() > 0.015  # it did smooth
    noise = np.random.default_rng(0).standard_normal((h, w, 1)).astype(np.float32)
    assert smoothing.axially_smoothed(noise, (cx, cy), (4.0, 0.75))[r < 28].std() < 0.25


def pairs_of(spec, scene, real: np.ndarray, sim: np.ndarray, **effects) -> Pairs:
    camera, ref, depth = scene
    records = [{"id": f"{i:06d}", "object": ("sphere", "cylinder")[i % 2], "path": i // 4, "position": i % 4}
               for i in range(len(depth))]
    return Pairs(Path("real"), Path("sim"), {}, {"renderer": renderer(**effects)}, [r["id"] for r in records],
                 records, real.astype(np.float32), sim.astype(np.float32), depth, spec)


@pytest.mark.parametrize("hidden, value, name", [pytest.param({"core_light_leak": {"fraction": 0.3}}, 0.3,
                                                              "core_light_leak", marks=pytest.mark.slow),
                                                 ({"absorption_per_m": {"value": 60.0}}, 60.0, "absorption_per_m"),
                                                 ({"core_light_leak": {"fraction": 0.3, "exposure": 1.06}}, 0.3,
                                                  "core_light_leak")])
def test_the_diagnosis_names_the_hidden_physical_effect(spec, scene, stub, hidden, value, name):
    sim = rendered(spec, scene, {})
    real = rendered(spec, scene, hidden)
    pairs = pairs_of(spec, scene, real, sim)
    train, heldout = split(pairs, 0.5, seed=0)
    d = Diagnosis(pairs, train, heldout, factor=4,
                  effects=("core_light_leak", "absorption_per_m", "led_power", "camera_gains", "sensor_noise"))
    assert d.work.kind == "pbr" and "sensor_noise" in d.not_applicable
    singles = d.singles()
    ranked = [n for n, j in sorted(singles.items(), key=lambda kv: -kv[1].gain) if j.significant]
    assert ranked[0] == name
    fitted = next(iter(singles[name].fit.params[name].values()))
    assert fitted == pytest.approx(value, rel=0.1)
    # The capture's exposure is fitted with it: the rule's where the capture followed it.
    assert singles[name].fit.params[name]["exposure"] == pytest.approx(hidden[name].get("exposure", 1.0), abs=0.01)
    assert singles[name].improvement["masked"]["mae"]["share"] > 0.8
    # Judged at the basis film: held-out images are its block means.
    assert d.judging.real_h.shape[1:3] == (FILM[1], FILM[0]) and d.full.factor == 8


@pytest.mark.parametrize("hidden, first", [({"core_leak_cone_rad": {"value": 0.3, "fraction": 0.3}},
                                             "core_leak_cone_rad"),
                                            pytest.param({"core_light_leak": {"fraction": 0.3}}, "core_light_leak",
                                                         marks=pytest.mark.slow)])
def test_a_leak_aimed_up_the_tube_is_a_candidate_though_the_simulation_has_no_leak(spec, scene, stub, hidden, first):
    """Without a leak in the simulation the leak's cone has nothing to shape, so it is
    fitted with a fraction of its own: it finds a hidden cone, and a plain leak (its cone
    at 0, the simulation's) ties with it and ranks first, being simpler."""
    sim = rendered(spec, scene, {})
    real = rendered(spec, scene, hidden)
    pairs = pairs_of(spec, scene, real, sim)
    train, heldout = split(pairs, 0.5, seed=0)
    d = Diagnosis(pairs, train, heldout, factor=4, effects=("core_light_leak", "core_leak_cone_rad", "camera_gains"))
    assert "core_leak_cone_rad" not in d.not_applicable
    assert [p.name for p in d.work.catalogue["core_leak_cone_rad"].params[:2]] == ["value", "fraction"]
    singles = d.singles()
    assert d.rank(singles)[0] == first
    cone = singles["core_leak_cone_rad"].fit.params["core_leak_cone_rad"]
    assert cone["fraction"] == pytest.approx(0.3, rel=0.1)
    assert cone["value"] == pytest.approx(hidden.get("core_leak_cone_rad", {"value": 0.0})["value"], abs=0.05)
    if first == "core_leak_cone_rad":  # a Lambertian leak cannot put the cone's light where it goes
        closes = {n: singles[n].improvement["masked"]["mae"]["share"] for n in ("core_light_leak", first)}
        assert closes[first] > 0.95 and closes["core_light_leak"] < closes[first] - 0.05


def test_a_reference_model_is_judged_at_its_basis_film(spec):
    from studies.gap.diagnosis import judging_factor

    assert judging_factor(spec, (80, 60)) == 8 and judging_factor(spec, (160, 120)) == 4
    assert judging_factor(spec, (100, 60)) == 1  # a film that does not tile the image: the images' own


def test_the_physical_benchmark_hides_every_effect_once_with_settings_the_renderer_takes(spec):
    from rig.cli import _unit
    from rig.virtual import unit_spec
    from studies.gap.physical import physical_catalogue
    from studies.gap.physical_benchmark import HIDDEN, UNIT_HIDDEN, WITH, capture_settings, draw

    drawn = [draw(case, seed=3) for case in range(len(HIDDEN) + 4)]
    assert sorted(next(iter(d)) for d in drawn[: len(HIDDEN)]) == sorted(HIDDEN)
    assert all(len(d) == 1 + (next(iter(d)) in WITH) for d in drawn[: len(HIDDEN)])
    assert draw(5, seed=3) == drawn[5]  # seeded
    few = [draw(case, seed=3, cases=12) for case in range(12)]  # fewer cases than effects: still every one
    assert set(name for d in few for name in d) == set(HIDDEN) and max(len(d) for d in few) >= 2
    assert all(WITH[n] in d for d in drawn + few for n in d if n in WITH)  # a cone is never hidden without its leak
    drawn += few
    assert set(HIDDEN) <= set(physical_catalogue(spec, Effects())[0])  # each a candidate of the diagnosis, by name
    for hidden in drawn:
        settings, unit_settings = capture_settings(hidden)
        effects = Effects().with_settings(settings)
        unit, compliance = unit_spec(spec, unit_settings)
        for name, value in hidden.items():
            if name == "membrane_compliance":
                assert compliance == value and 0.75 <= value <= 1.25 and abs(value - 1) >= 0.15
            elif name == "layer_spread":
                assert unit.elastic.poisson_ratio == value
            elif name == "led_peak_shift":
                assert [b.peak_nm - a.peak_nm for a, b in zip(spec.leds, unit.leds)] == pytest.approx([value] * 3)
                assert 8 <= abs(value) <= 20
            elif name == "camera_gains":
                assert _unit([f"camera_gains={','.join(map(str, value))}"])[name] == value
                assert all(0.1 <= abs(g - 1) <= 0.3 for g in value)
            elif name == "alignment":
                assert all(2 <= abs(d) <= 6 for d in value[:2]) and 0.01 <= abs(value[2]) <= 0.04
            elif name == "blur":
                assert 1.5 <= value <= 3.5
            elif name == "led_power":  # LEDs of another bin: their ratios change, not only all of them
                assert _unit([f"led_power={','.join(map(str, value))}"])[name] == value and len(value) == 3
                assert all(0.2 <= abs(p - 1) <= 0.45 for p in value) and unit == spec
            else:
                assert name not in UNIT_HIDDEN and getattr(effects, name) == value


def test_a_reference_case_that_is_mostly_monte_carlo_noise_is_listed_apart():
    """Both renders' noise is in a reference case's gap and no candidate closes it: a case
    whose gap is mostly that noise (sqrt(2) x the replay's judged floor) is set apart, and
    the others are scored on their own."""
    from studies.gap.physical_benchmark import RESIDUAL_SHARE, _against_noise, score_physical

    def report(gap, first):
        closes = {"full": 0.1, "masked": 0.3}
        return {"model": "pbr", "ranking": [first, "alignment"], "gap": {"heldout": {"masked": {"mae": {"mean": gap}}}},
                "explained": {"effects": [first], "share_closed": closes},
                "effects": {first: {"share_closed": closes, "params": {first: 1.06, "exposure": 1.0}}},
                "noise": {"mae_floor": 0.004, "monte_carlo": {"judged": {"mae_floor": {"sim": 0.005}}}}}

    quiet = score_physical({"membrane_compliance": 1.17}, report(0.0078, "alignment"))
    loud = score_physical({"led_peak_shift": 14.6}, report(0.0435, "led_peak_shift"))
    assert quiet["noise_floor"] == pytest.approx(0.005 * 2**0.5) and quiet["noise_floor_share"] >= RESIDUAL_SHARE
    assert loud["noise_floor_share"] == pytest.approx(0.005 * 2**0.5 / 0.0435) and loud["fitted"] == {"led_peak_shift": 1.06}
    summary = _against_noise([{**quiet, "case": 0}, {**loud, "case": 1}])
    assert summary["below_noise"] == [0] and summary["above_noise"]["cases"] == 1
    assert summary["above_noise"]["top1"] == 1.0 and summary["above_noise"]["mean_heldout_shrink"] == 0.3
    # A measured floor (two renders of the same physics) replaces that lower bound.
    measured = score_physical({"led_peak_shift": 14.6}, report(0.0435, "led_peak_shift"), floor=0.037)
    assert measured["noise_floor"] == 0.037 and measured["noise_floor_bound"] == pytest.approx(0.005 * 2**0.5)
    assert _against_noise([{**measured, "case": 1}])["below_noise"] == [1]


def test_a_hidden_leak_aimed_up_the_tube_is_named_by_the_cones_candidate_alone():
    """Its candidate carries the leak's fraction, so a case hiding a leak and its cone is
    scored on the cone's candidate, which gives both fitted values."""
    from studies.gap.physical_benchmark import score_physical

    cone = {"value": 0.296, "fraction": 0.485, "exposure": 0.7}
    report = {"model": "pbr", "ranking": ["core_leak_cone_rad", "camera_gains", "led_power", "core_light_leak"],
              "gap": {"heldout": {"masked": {"mae": {"mean": 0.2}}}},
              "explained": {"effects": ["core_leak_cone_rad"], "share_closed": {"masked": 0.96}},
              "effects": {"core_leak_cone_rad": {"share_closed": {"masked": 0.96},
                                                 "params": {"core_leak_cone_rad": cone}},
                          "core_light_leak": {"share_closed": {"masked": 0.6}, "params": {"core_light_leak": {}}}}}
    scored = score_physical({"core_light_leak": 0.459, "core_leak_cone_rad": 0.2957}, report)
    assert scored["top1"] and scored["top3"] and scored["fitted"] == {"core_leak_cone_rad": cone}
    alone = score_physical({"core_light_leak": 0.459}, report)  # a Lambertian leak is its own candidate's
    assert not alone["top1"] and not alone["top3"]


def test_a_fast_diagnosis_of_a_physical_case_is_scored_on_the_counterparts():
    """The realistic pairing: the hidden physical effects are scored through their fast
    catalogue counterparts, and the per-region shares they close are kept."""
    from studies.gap.physical import COUNTERPARTS
    from studies.gap.physical_benchmark import _per_region, counterparts, score_physical

    hidden = {"absorption_per_m": 90.0, "scattering_per_m": 200.0}
    assert counterparts(hidden) == ["path_attenuation"]  # each counterpart once
    closes = {"full": 0.2, "masked": 0.6, "tip": 0.8, "body": 0.3, "near_leds": 0.1}
    report = {"model": "fast", "ranking": ["path_attenuation", "vignetting"],
              "gap": {"heldout": {"masked": {"mae": {"mean": 0.02}}}},
              "explained": {"effects": ["path_attenuation"], "share_closed": closes},
              "effects": {"path_attenuation": {"share_closed": closes, "params": {"mu_per_m": 80.0}}}}
    out = score_physical(hidden, report)
    assert out["top1"] and out["top3"] and out["counterparts"] == ["path_attenuation"]
    assert out["fitted"] == {"path_attenuation": {"mu_per_m": 80.0}} and out["closes"]["path_attenuation"]["tip"] == 0.8
    wrong = score_physical({"vignetting": 0.4}, {**report, "ranking": ["path_attenuation", "blur_noise"]})
    assert not wrong["top1"] and not wrong["top3"] and COUNTERPARTS["vignetting"] == "vignetting"
    regions = _per_region([{**out, "hidden": list(hidden)}, {**out, "hidden": ["absorption_per_m"],
                                                            "closes": {"path_attenuation": {**closes, "tip": 0.4}}}])
    assert regions["absorption_per_m"]["tip"] == pytest.approx(0.6) and "full" not in regions["absorption_per_m"]
    # the calibration's own residual: a case whose gap it makes is set apart
    from studies.gap.physical_benchmark import RESIDUAL_SHARE, _against_residual

    cases = [{**out, "hidden": list(hidden), "case": 0}, {**wrong, "hidden": ["vignetting"], "case": 1, "gap": 0.0101}]
    summary = _against_residual(cases, 0.01, ["path_attenuation"])
    assert cases[0]["residual_share"] == pytest.approx(0.5) and cases[1]["residual_share"] >= RESIDUAL_SHARE
    assert summary["below_residual"] == [1] and summary["above_residual"]["cases"] == 1
    assert summary["above_residual"]["top1"] == 1.0 and summary["residual"]["heldout_masked_mae"] == 0.01
    # a reference diagnosis is scored on the hidden effects themselves
    ref = score_physical({"absorption_per_m": 90.0}, {"ranking": ["absorption_per_m"], "explained": report["explained"],
                                                      "gap": report["gap"],
                                                      "effects": {"absorption_per_m": {
                                                          "share_closed": closes, "params": {"absorption_per_m": 85.0}}}})
    assert ref["top1"] and ref["fitted"] == {"absorption_per_m": 85.0} and "closes" not in ref
    assert ref["noise_floor"] is None and ref["noise_floor_share"] == 0.0  # no variance maps: not set apart


def test_the_renders_monte_carlo_noise_floor_comes_from_their_variance_maps(spec, scene, tmp_path):
    from studies.gap.diagnose import render_noise

    camera, ref, depth = scene
    n = 2
    image = np.zeros((n,) + camera.shape + (3,), np.float32)
    pairs = pairs_of(spec, scene, image, image).subset(np.arange(n))
    pairs.real_dir, pairs.sim_dir = tmp_path / "real", tmp_path / "sim"
    pairs.real_meta = {"renderer": renderer()}
    for root, v in ((pairs.real_dir, 1e-4), (pairs.sim_dir, 3e-4)):
        (root / "variance").mkdir(parents=True)
        for i in pairs.ids:
            np.save(root / "variance" / f"{i}.npy", np.full(camera.shape + (3,), v / GAIN**2, np.float32))
    out = render_noise(pairs, np.arange(n), camera.mask)
    assert out["mae_floor"]["real"] == pytest.approx(np.sqrt(2 / np.pi) * 1e-2, rel=1e-4)
    assert out["mae_floor_difference"] == pytest.approx(np.sqrt(2 / np.pi) * 2e-2, rel=1e-4)
    # Block means of 8x8 pixels of a film as large as the image: 64 independent pixels each.
    judged = render_noise(pairs, np.arange(n), camera.mask, factor=8)["judged"]
    assert judged["mae_floor"]["real"] == pytest.approx(np.sqrt(2 / np.pi) * 1e-2 / 8, rel=1e-4)
    pairs.real_meta["renderer"]["film"] = [160, 120]  # 2x2 film pixels in a block
    judged = render_noise(pairs, np.arange(n), camera.mask, factor=8)["judged"]
    assert judged["mae_floor"]["real"] == pytest.approx(np.sqrt(2 / np.pi) * 1e-2 / 2, rel=1e-4)
    # Low-passed as the reference model compares them: a Gaussian of one block, whose
    # squared weights sum to (sum_x g(x)^2)^2 for the 1-D kernel g (truncated at 4 sigma).
    g = np.exp(-0.5 * np.arange(-4, 5) ** 2)
    g /= g.sum()
    low = render_noise(pairs, np.arange(n), camera.mask, factor=8, sigma=1.0)["judged"]
    assert low["mae_floor"]["real"] == pytest.approx(judged["mae_floor"]["real"] * float(np.sum(g ** 2)), rel=1e-4)
    (pairs.real_dir / "variance" / f"{pairs.ids[1]}.npy").unlink()
    assert render_noise(pairs, np.arange(n), camera.mask)["sides"] == ["sim"]


def test_the_physical_benchmark_refuses_to_be_mixed_with_the_stratified_one(tmp_path, capsys):
    from scenes.cli import main

    assert main(["diagnose", "benchmark", "--physical", "--stratified", "--json", str(tmp_path / "b.json")]) == 2
    assert "--physical and --stratified are separate benchmarks" in capsys.readouterr().err
    assert main(["diagnose", "benchmark", "--pairing", "fast", "--json", str(tmp_path / "b.json")]) == 2
    assert "--pairing needs --physical" in capsys.readouterr().err
    from studies.gap.physical_benchmark import run_physical_benchmark

    with pytest.raises(ValueError, match="pairing must be one of"):
        run_physical_benchmark(cases=1, work=tmp_path / "w", pairing="phong")
    assert not (tmp_path / "w").exists()
    assert not (tmp_path / "b.json").exists()


def test_the_physical_bench_times_the_diagnosis_alone_on_its_capture_and_replay(tmp_path, monkeypatch, capsys):
    """``bench diagnose --physical``: the capture (with the hidden leak) and the replay of
    ``--pairs`` taps are made first and timed apart, then the whole diagnosis of the pair
    is timed; the result names what came first and what the hidden leak closed. The
    renders and the diagnosis are stood in for here (each is tested on its own)."""
    import studies.gap.diagnose as dg
    import studies.gap.physical_benchmark as pb
    from scenes.cli import main

    made = []
    monkeypatch.setattr(pb, "capture", lambda folder, hidden, progress=False, taps=pb.TAPS:
                        made.append(("capture", dict(hidden), taps)) or folder)
    monkeypatch.setattr(pb, "replay", lambda real, folder, progress=False: made.append(("replay", real.name)) or folder)
    monkeypatch.setattr(dg, "run", lambda real, sim, out, seed=0, progress=True: {
        "pairs": 36, "ranking": ["core_light_leak"], "model": "pbr", "renders": {"count": 3},
        "effects": {"core_light_leak": {"share_closed": {"masked": 0.5}, "params": {"fraction": 0.29}}}})
    out = tmp_path / "bench.json"
    assert main(["bench", "diagnose", "--physical", "--work", str(tmp_path / "w"), "--json", str(out), "--quiet"]) == 0
    assert made == [("capture", pb.BENCH_HIDDEN, 36), ("replay", "real_36")]
    result = json.loads(out.read_text())
    assert result["first"] == "core_light_leak" and result["pairs"] == 36 and result["cold"]
    assert result["seconds"] >= 0 and result["setup_seconds"] >= 0
    assert result["hidden_share_closed"] == {"masked": 0.5}
    with pytest.raises(ValueError, match="pairs must be >= 4"):
        pb.bench_physical(pairs=2, work=tmp_path / "w")


@pytest.mark.slow
def test_re_rendered_candidates_beyond_the_best_on_training_are_not_judged(spec, scene, stub, monkeypatch):
    """Judging a re-rendered candidate renders every held-out tap: only the best
    ``JUDGED_RENDERS`` of them on the training taps are; the rest are screened out, say
    why, close nothing and are never ranked, and none of their held-out taps is rendered.
    Each is first fitted on ``SCREEN_TAPS`` of the fit's taps: the ones screened out
    trace their grid on those alone."""
    from studies.gap.diagnose import diagnose
    from studies.gap.report import headline

    monkeypatch.setattr(reference_model, "JUDGED_RENDERS", 1)
    monkeypatch.setattr(source_basis, "REWEIGHTED", ())  # every grid point traced, as a glossy paint's are
    pairs = pairs_of(spec, scene, rendered(spec, scene, {"absorption_per_m": {"value": 60.0}}), rendered(spec, scene, {}))
    train, heldout = split(pairs, 0.5, seed=0)
    d = Diagnosis(pairs, train, heldout, factor=8,
                  effects=("core_light_leak", "absorption_per_m", "scattering_per_m", "coating_albedo"))
    singles = d.singles()
    screened = {n for n, j in singles.items() if "screened" in j.fit.status}
    assert screened == {"scattering_per_m", "coating_albedo"}
    assert singles["absorption_per_m"].significant
    # More were to be traced again than are judged: each was screened on SCREEN_TAPS of the
    # fit's taps first, and only the best there was fitted on all of them.
    screen_taps = set(d._screen.train_index.tolist())
    assert len(screen_taps) == reference_model.SCREEN_TAPS < len(d.train_index)
    assert screen_taps <= set(d.train_index.tolist())
    for name in screened:
        assert not singles[name].significant and singles[name].gain == 0.0
        assert "absorption_per_m" in singles[name].fit.status["screened"]
        assert singles[name].fit.status["screen"]["taps"] == reference_model.SCREEN_TAPS
        rendered_keys = {tag[0] for tag in d.work.basis._images if tag[1] == name}
        assert rendered_keys and rendered_keys <= screen_taps | {source_basis.NO_CONTACT}
    fitted = {tag[0] for tag in d.work.basis._images if tag[1] == "absorption_per_m"}
    assert set(d.train_index.tolist()) <= fitted
    assert singles["absorption_per_m"].fit.status["screen"]["train_loss"] < \
        singles["absorption_per_m"].fit.status["screen"]["train_loss_before"]
    assert d.rank(singles)[0] == "absorption_per_m"
    report, _ = diagnose(pairs, effects=d.effects, factor=8, intervals=0)
    assert set(report["screened"]) == screened and not set(report["ranking"]) & screened
    assert any("not judged on the held-out taps" in line for line in headline(report))


def test_a_reference_diagnosis_writes_its_report_judged_at_the_basis_film(spec, scene, stub, tmp_path):
    from studies.gap.diagnose import diagnose, heldout_gap
    from studies.gap.report import headline, write_report

    pairs = pairs_of(spec, scene, rendered(spec, scene, {"core_light_leak": {"fraction": 0.3}}), rendered(spec, scene, {}))
    report, artefacts = diagnose(pairs, effects=("core_light_leak", "blur"))
    assert report["model"] == "pbr" and report["settings"]["judged_at"] == list(FILM)
    assert heldout_gap(pairs) == report["gap"]["heldout"]["masked"]["mae"]["mean"] > 0  # the benchmark's floor
    assert report["ranking"][0] == "core_light_leak"
    write_report(tmp_path, report, artefacts)  # figures mix full-resolution maps and judged examples
    assert (tmp_path / "report.html").is_file() and (tmp_path / "gap_maps.png").is_file()
    assert any("judged at 80x60" in line for line in headline(report))
    # The best-ranked effects' parameters come with bootstrap intervals over the training taps.
    # (Noise-free stand-in images: the resampled fits all lie close to the hidden 0.3.)
    low, high = report["effects"]["core_light_leak"]["param_intervals"]["core_light_leak"]["fraction"]
    fitted = report["effects"]["core_light_leak"]["params"]["core_light_leak"]["fraction"]
    assert 0.28 < low <= high < 0.32 and low - 0.01 < fitted < high + 0.01
    # The basis' own Monte Carlo noise is stated beside the bar a candidate must clear.
    basis = report["noise"]["basis"]
    assert basis["taps"] >= 2 and basis["mae_floor"] > 0 and basis["min_gain"] == report["settings"]["min_gain"]
    assert basis["under_min_gain"] == (basis["mae_floor"] < basis["min_gain"]) and basis["inscatter"] == "fluence"


def test_the_basis_noise_is_its_variance_as_the_images_are_compared(spec, scene, stub, monkeypatch):
    """``ReferenceModel.basis_noise``: a noise twice as large doubles the floor; a flat
    variance sigma^2 (per unit weight) low-passed by a Gaussian keeps sigma^2 times its
    squared weights' sum, so the floor is sqrt(2 / pi) sigma sqrt(sum w^2) inside the
    film's circle; nothing rendered, nothing stated."""
    from scipy import ndimage

    import test_gap_physical as me
    from studies.gap.reference_model import COMPARED_SIGMA_FILM_PX
    from studies.gap.source_basis import NO_CONTACT

    camera, ref, depth = scene
    model = ReferenceModel(spec, renderer(), 1, SourceBasis(spec, renderer(), depth, film=FILM))
    assert model.basis_noise([0, NO_CONTACT]) is None  # none rendered yet
    model.image(0, {})
    once = model.basis_noise([0, 1])
    assert once["taps"] == 1  # tap 1 is not rendered: left out, not rendered for this
    monkeypatch.setattr(me, "NOISE", 2 * NOISE)
    twice = ReferenceModel(spec, renderer(), 1, SourceBasis(spec, renderer(), depth, film=FILM))
    twice.image(0, {})
    assert twice.basis_noise([0])["mae_floor"] == pytest.approx(2 * once["mae_floor"], rel=1e-5)
    flat = np.ones(FILM[::-1] + (len(twice.basis.names),), np.float32)
    twice.basis._variances[(0, None, None)] = flat
    weight = (GAIN * twice.colour({})) ** 2  # (S, 3)
    impulse = np.zeros((41, 41))
    impulse[20, 20] = 1.0
    kept = (ndimage.gaussian_filter(impulse, COMPARED_SIGMA_FILM_PX) ** 2).sum()
    inside = twice._film.mask
    expected = np.sqrt(2 / np.pi) * np.mean(np.broadcast_to(np.sqrt(weight.sum(axis=0) * kept), inside.shape + (3,))[inside])
    assert twice.basis_noise([0])["mae_floor"] == pytest.approx(expected, rel=0.02)


def test_the_reference_lens_is_judged_with_the_exposure_its_capture_gets(spec, scene, stub):
    """A vignetted reference capture is exposed after the lens, from its own no-contact
    frame: its centre brightens while its edge keeps the level; the model predicts that."""
    from pbr_tactile import sensor
    from pbr_tactile.plugin import EXPOSURE_PERCENTILE

    camera, ref, depth = scene
    model = ReferenceModel(spec, renderer(), 1, SourceBasis(spec, renderer(), depth, film=FILM))
    frames = np.stack([model._resized(model.image(i, {})) for i in range(len(depth))])
    nc = model._resized(model.image(source_basis.NO_CONTACT, {}))
    lens = sensor.vignetting(nc, camera, 0.5)
    gain = np.percentile(nc[camera.mask], EXPOSURE_PERCENTILE) / np.percentile(lens[camera.mask], EXPOSURE_PERCENTILE)
    real = np.clip(gain * np.stack([sensor.vignetting(f, camera, 0.5) for f in frames]), 0, 1)
    pairs = pairs_of(spec, scene, real, frames)
    train, heldout = split(pairs, 0.5, seed=0)
    d = Diagnosis(pairs, train, heldout, factor=4, effects=("vignetting", "core_light_leak", "camera_gains"))
    singles = d.singles()
    best = max(singles, key=lambda n: singles[n].gain)
    assert best == "vignetting"
    assert singles[best].fit.params[best]["strength"] == pytest.approx(0.5, abs=0.05)
    assert singles[best].fit.params[best]["exposure"] == pytest.approx(1.0, abs=0.02)


def test_a_reference_ranking_puts_the_simplest_of_the_tied_best_first(spec, scene, stub):
    """camera_gains (a colour matrix, 11 parameters) and the LEDs' powers (3) both undo
    a colour change of the LEDs; when the first is not significantly better, the LEDs
    come first."""
    sim = rendered(spec, scene, {})
    real = rendered(spec, scene, {"led_power": {"power_0": 1.3, "power_1": 1.0, "power_2": 0.8}})
    pairs = pairs_of(spec, scene, real, sim)
    train, heldout = split(pairs, 0.5, seed=0)
    d = Diagnosis(pairs, train, heldout, factor=8, effects=("led_power", "camera_gains"))
    singles = d.singles()
    by_gain = sorted(singles, key=lambda n: -singles[n].gain)
    ranked = d.rank(singles)
    assert set(ranked) == {"led_power", "camera_gains"} and ranked[0] == "led_power"
    if by_gain[0] == "camera_gains":  # then it must not have been better by more than the tie rule allows
        from studies.gap import metrics
        from studies.gap.selection import RANK_TIE_SHARE

        a, b = (singles[n].after["masked"]["mae"] for n in ("led_power", "camera_gains"))
        within = np.mean(a) - np.mean(b) <= RANK_TIE_SHARE * np.mean(d.before["masked"]["mae"])
        assert within or not metrics.improvement(a, b, "mae")["significant"]


def test_a_reference_candidate_within_the_tie_margin_of_the_best_ties_with_it():
    """camera_gains (11 parameters) better than a 1-parameter effect on every held-out tap
    (significant) by less than RANK_TIE_SHARE of the gap: the simpler one comes first; by
    more, camera_gains does."""
    from types import SimpleNamespace

    from studies.gap import selection
    from studies.gap.judge import Judged

    def judged(mae: np.ndarray, before: np.ndarray) -> Judged:
        from studies.gap import metrics

        after = {"masked": {"mae": mae}}
        return Judged(fit=None, after=after, improvement={"masked": {"mae": metrics.improvement(before, mae, "mae")}})

    rng = np.random.default_rng(0)
    before = 0.02 + 0.001 * rng.standard_normal(20)
    catalogue = {"camera_gains": SimpleNamespace(params=[SimpleNamespace(name=f"p{i}") for i in range(11)]),
                 "absorption_per_m": SimpleNamespace(params=[SimpleNamespace(name="value"),
                                                              SimpleNamespace(name="exposure")])}
    model = Diagnosis.__new__(Diagnosis)  # the ranking alone, on stated held-out errors
    model.__dict__.update(work=SimpleNamespace(kind="pbr", ties_to_simplest=True), catalogue=catalogue, seed=0,
                          before={"masked": {"mae": before}})
    best = 0.004 + 0.0005 * rng.standard_normal(20)
    for lag, first in ((0.5 * selection.RANK_TIE_SHARE, "absorption_per_m"), (3 * selection.RANK_TIE_SHARE, "camera_gains")):
        singles = {"camera_gains": judged(best, before),
                   "absorption_per_m": judged(best + lag * before.mean(), before)}
        assert model.rank(singles)[0] == first


@pytest.mark.slow
def test_two_hidden_colour_effects_are_ranked_first_as_a_pair_over_the_flexible_camera_model(spec, scene, stub):
    """LED peaks shifted and the camera's response off: a colour matrix with a curve
    (camera_gains, 11 parameters) mimics the two better than either alone; the pair (4
    parameters) closes as much, so it takes the first two places, at the hidden values."""
    sim = rendered(spec, scene, {})
    hidden = {"led_peak_shift": {"shift_nm_0": 15.0, "shift_nm_1": 15.0, "shift_nm_2": 15.0},
              "camera_response": {"on": 0.0}}
    pairs = pairs_of(spec, scene, rendered(spec, scene, hidden), sim)
    train, heldout = split(pairs, 0.5, seed=0)
    d = Diagnosis(pairs, train, heldout, factor=8, effects=("led_peak_shift", "camera_response", "camera_gains"))
    singles = d.singles()
    ranked = d.rank(singles)
    assert set(ranked[:2]) == set(hidden) and d.first_pair is not None
    assert d.first_pair.instead_of == "camera_gains"  # the single it displaced
    fitted = d.first_pair.fit.params
    # (a switch's blend: the low-passed comparison leaves its minimum shallow; 0.11 at sigma 1.25)
    assert fitted["camera_response"]["on"] == pytest.approx(0.0, abs=0.15)
    assert [fitted["led_peak_shift"][f"shift_nm_{m}"] for m in range(3)] == pytest.approx([15.0] * 3, abs=5.0)
    steps = d.select(singles, ranked)
    assert set(steps[1].fit.effects) == set(hidden)  # the selection goes on from the pair


def test_a_pair_takes_the_first_place_only_if_each_of_its_two_adds_to_the_other():
    """The rule on stated held-out errors: a 1+1-parameter pair as good as camera_gains
    (11) comes first; not if one of its two adds nothing to the other alone."""
    from types import SimpleNamespace

    from studies.gap import metrics
    from studies.gap.fit import Fit
    from studies.gap.judge import Judged

    rng = np.random.default_rng(0)
    before = 0.02 + 0.001 * rng.standard_normal(20)

    def judged(names: tuple, mae: np.ndarray) -> Judged:
        fit = Fit(names, {n: {"value": 1.0} for n in names}, 0.0, 0.0, 0, 0.0)
        return Judged(fit, {"masked": {"mae": mae}}, {"masked": {"mae": metrics.improvement(before, mae, "mae")}})

    one = [SimpleNamespace(name="value", identity=0.0), SimpleNamespace(name="exposure", identity=1.0)]
    catalogue = {"camera_gains": SimpleNamespace(params=[SimpleNamespace(name=f"p{i}") for i in range(11)]),
                 "absorption_per_m": SimpleNamespace(params=one), "coating_albedo": SimpleNamespace(params=one)}
    best = 0.004 + 0.0005 * rng.standard_normal(20)
    for albedo_alone, first in ((0.012, "absorption_per_m"), (0.006, "camera_gains")):
        singles = {"camera_gains": judged(("camera_gains",), best),
                   "absorption_per_m": judged(("absorption_per_m",), best + 0.006),
                   "coating_albedo": judged(("coating_albedo",), best + albedo_alone)}
        pair = judged(("absorption_per_m", "coating_albedo"), best + 0.006 - (0.006 if first != "camera_gains" else 0))
        d = Diagnosis.__new__(Diagnosis)
        d.__dict__.update(work=SimpleNamespace(kind="pbr", ties_to_simplest=True), catalogue=catalogue, seed=0,
                          before={"masked": {"mae": before}}, names=tuple(catalogue),
                          fit=lambda names, start=None, free=None, max_iterations=0: pair.fit,
                          judge=lambda fit, against=None, complete=True: pair)
        ranked = d.rank(singles)
        assert ranked[0] == first and (d.first_pair is not None) == (first != "camera_gains")


def test_an_alignment_closes_the_simulations_noise_only_where_it_is_compared_unsmoothed(spec, scene, stub,
                                                                                          monkeypatch):
    """Over a noisy simulation, an alignment fits a sub-pixel displacement whose
    interpolation smooths the noise, and so closes part of a gap that is all noise; the
    reference model compares its images low-passed (``compared``), where it closes (almost)
    none of it, while a real displacement is still found and closed."""
    clean = rendered(spec, scene, {})
    rng = np.random.default_rng(1)

    def noisy(images: np.ndarray) -> np.ndarray:  # white noise at the judged film's pixels
        noise = np.repeat(np.repeat(rng.normal(0.0, 0.01, (len(images), FILM[1], FILM[0], 3)), 8, 1), 8, 2)
        return np.clip(images + noise, 0.0, 1.0).astype(np.float32)

    def alignment(real: np.ndarray, sim: np.ndarray):
        pairs = pairs_of(spec, scene, real, sim)
        train, heldout = split(pairs, 0.5, seed=0)
        return Diagnosis(pairs, train, heldout, factor=8, effects=("alignment",)).singles()["alignment"]

    real, sim = noisy(clean), noisy(clean)
    low = alignment(real, sim).improvement["masked"]["mae"]
    monkeypatch.setattr(reference_model, "COMPARED_SIGMA_FILM_PX", 0.0)  # the images themselves
    raw = alignment(real, sim).improvement["masked"]["mae"]
    monkeypatch.undo()
    assert raw["significant"] and raw["share"] > 0.03
    assert low["share"] < raw["share"] / 3
    model = ReferenceModel(spec, renderer(), 1, SourceBasis(spec, renderer(), scene[2], film=FILM))
    moved = model.optics(clean, {"alignment": {"du_px": 6.0, "dv_px": -4.0, "rotation_rad": 0.03, "scale": 1.0}})
    found = alignment(noisy(moved), noisy(clean))
    assert found.significant and found.improvement["masked"]["mae"]["share"] > 0.3  # the rest is the noise
    fitted = found.fit.params["alignment"]
    assert (fitted["du_px"], fitted["dv_px"]) == pytest.approx((6.0, -4.0), abs=1.5)
    assert fitted["rotation_rad"] == pytest.approx(0.03, abs=0.01)


def test_medium_and_paint_grid_points_are_reweighted_from_one_render_per_tap(spec, scene, stub, monkeypatch):
    """Absorption, scattering and the paint's albedo change how much light survives a
    path, not the path: each tap's identity render re-weights its photons to every grid
    point of them (issue 74), so a fit over those grids renders each tap once. A point
    whose re-weighting is not valid (ESS ratio below the bound) is traced again, and the
    basis says which."""
    import pbr_tactile.basis

    camera, ref, depth = scene
    calls = []

    def counted(*args, **kwargs):
        calls.append(kwargs.get("perturb") is not None)
        return fake_basis(*args, **kwargs)

    monkeypatch.setattr(pbr_tactile.basis, "emitter_basis", counted)
    monkeypatch.setitem(ESS, (20.0, 250.0, 0.85), 0.01)  # scattering 250 re-weights too noisily
    basis = SourceBasis(spec, renderer(), depth, film=FILM)
    assert basis.reweighting["on"] and "scattering_per_m=250" in basis.reweighting["variants"]
    grids = physical_catalogue(spec, basis.effects)[2]
    for key in (0, 1):
        for name in source_basis.REWEIGHTED:
            for value in grids[name]["values"]:
                if value == getattr(basis.effects, name):
                    continue  # the identity's own image (``ReferenceModel.interpolated`` reads it so)
                got = basis.images(key, name, value)
                _, effects, _ = basis.variant(name, value)
                expected = fake_basis(spec, basis.mesh, basis.camera, effects, FILM, depth=depth[key], ref_depth=ref)
                assert np.allclose(got, expected["mean"], rtol=1e-6), (name, value)
    # Per tap: one render with the variants, one more for the point that was not valid.
    assert calls == [True, False, True, False]
    assert basis.reweighting["retraced"] == {"scattering_per_m=250": {"tap": 0, "ess_ratio": 0.01}}
    assert set(basis.cost) == {"identity", "scattering_per_m"}
    model = ReferenceModel(spec, renderer(), 1, basis)
    assert not model.costly("absorption_per_m") and not model.costly("coating_albedo")
    assert model.costly("scattering_per_m") and model.costly("membrane_compliance")  # one point traced; a dent moves


def test_a_leaks_cone_traces_the_leaks_alone_beside_the_identitys_leds(spec, scene, stub, monkeypatch):
    """The leak's cone changes only the leaks' light: its grid points render the leak
    sources alone (``emitter_basis(only=)``) and take the LEDs' own columns from the
    identity's render, which is what a render of every source there gives."""
    import pbr_tactile.basis

    camera, ref, depth = scene
    calls = []

    def counted(*args, **kwargs):
        calls.append(kwargs.get("only"))
        return fake_basis(*args, **kwargs)

    monkeypatch.setattr(pbr_tactile.basis, "emitter_basis", counted)
    basis = SourceBasis(spec, renderer(core_light_leak=0.3), depth, film=FILM)
    for key in (source_basis.NO_CONTACT, 0):
        got = basis.images(key, "core_leak_cone_rad", 0.3)
        _, effects, _ = basis.variant("core_leak_cone_rad", 0.3)
        whole = fake_basis(spec, basis.mesh, basis.camera, effects, FILM,
                           **({} if key == source_basis.NO_CONTACT else {"depth": depth[key], "ref_depth": ref}))
        np.testing.assert_allclose(got, whole["mean"], rtol=1e-6)
        np.testing.assert_allclose(basis._variances[(key, "core_leak_cone_rad", 0.3)], whole["variance"], rtol=1e-6)
    leaks = [k for k, n in enumerate(basis.names) if n.endswith("_leak")]
    assert len(leaks) == len(spec.leds) and calls == [None, leaks, None, leaks]  # the identity first, each tap
    assert not np.allclose(basis.images(0, "core_leak_cone_rad", 0.3), basis.images(0))  # the cone is seen


@pytest.mark.slow
def test_a_render_of_the_leaks_alone_is_the_whole_renders_leak_columns(spec, scene, tmp_path, monkeypatch, photon_mi):
    """``emitter_basis(only=)`` on the reference itself (a contact, no-contact runs, the
    fluence): the leak sources traced alone give the columns a render of every source
    gives them, to float rounding (the same random numbers), in a fraction of its time."""
    from pbr_tactile.basis import emitter_basis
    from scenes.cache import CACHE_ENV

    monkeypatch.setenv(CACHE_ENV, str(tmp_path))
    camera, ref, depth = scene
    effects = Effects(core_light_leak=0.5, core_leak_cone_rad=0.3)
    kw = dict(film=(16, 12), photons=1 << 12, spp=4, passes=2, seed=1, no_contact_runs=1, depth=depth[0],
              ref_depth=ref)
    mesh = membrane_mesh(spec)
    whole = emitter_basis(spec, mesh, camera, effects, **kw)
    leaks = [k for k, n in enumerate(whole["names"]) if str(n).endswith("_leak")]
    alone = emitter_basis(spec, mesh, camera, effects, only=leaks, **kw)
    assert list(alone["names"]) == [whole["names"][k] for k in leaks]
    np.testing.assert_allclose(alone["mean"], whole["mean"][..., leaks], rtol=1e-5, atol=1e-6 * whole["mean"].max())
    np.testing.assert_allclose(alone["variance"], whole["variance"][..., leaks], rtol=1e-4,
                               atol=1e-6 * whole["variance"].max())
    np.testing.assert_allclose(alone["response"], whole["response"][leaks])


def test_a_glossy_paints_albedo_is_traced_and_its_medium_reweighted(spec, scene, stub):
    """A glossy paint's flake bounces do not scale with its albedo, so its albedo's grid
    points are traced (costly, screened); its medium's are re-weighted. Where the
    simulation's medium does not scatter, its scattering's points are traced too."""
    camera, ref, depth = scene
    basis = SourceBasis(spec, renderer(coating_gloss=0.3), depth, film=FILM)
    assert basis.reweighting["on"] and {n for n, _ in basis.variants} == {"absorption_per_m", "scattering_per_m"}
    assert "glossy" in basis.reweighting["not_reweighted"]["coating_albedo"]
    model = ReferenceModel(spec, renderer(coating_gloss=0.3), 1, basis)
    assert model.costly("coating_albedo") and not model.costly("absorption_per_m")
    clear = SourceBasis(spec, renderer(coating_gloss=0.3, scattering_per_m=0.0), depth, film=FILM)
    assert {n for n, _ in clear.variants} == {"absorption_per_m"}
    assert set(clear.reweighting["not_reweighted"]) == {"coating_albedo", "scattering_per_m"}
    assert "does not scatter" in clear.reweighting["not_reweighted"]["scattering_per_m"]


def _profiled(spec) -> dict:
    """The stand-in's renderer settings as a replay through a unit's profile records them:
    its per-LED gains and leak, a camera response, no exposure gain."""
    from scenes.profile import CameraProfile, Profile

    leds = len(spec.leds)
    gains = (np.array([[1.2, 0.9, 0.7], [0.8, 1.1, 0.9], [0.7, 0.9, 1.3]] * leds)[:leds] * 0.004).tolist()
    profile = Profile(sensor=spec.name, leds=tuple(led.name for led in spec.leds), camera=CameraProfile(gamma=1.6),
                      reference={"led_gains": gains, "led_leak": [0.2] * leds})
    return {**renderer(core_light_leak=0.5), "exposure_gain": None, "profile": "unit/profile.toml",
            "profile_data": profile.to_dict()}


def test_a_replay_through_a_units_profile_is_modelled_through_its_camera(spec, scene, stub):
    """A replay through a unit's profile is imaged by the profile's camera (per-LED gains,
    leak, response): the per-source model images its candidates through it, and leaves out
    the light's candidates, which the profile's gains stand for. A lens candidate is
    predicted without the reference's exposure rule, which a profile replaces (run for
    real, it asked for that rule's gain: a TypeError)."""
    from scenes.profile import profile_from_dict
    from studies.gap.diagnosis import make_models

    profiled = _profiled(spec)
    profile = profile_from_dict(profiled["profile_data"])
    camera, ref, depth = scene
    model = ReferenceModel(spec, profiled, 1, SourceBasis(spec, profiled, depth, film=FILM), profile)
    sim, real = (np.stack([model._resized(model.image(i, p)) for i in range(len(depth))])
                 for p in ({}, {"absorption_per_m": {"value": 60.0}}))
    assert 0.05 < sim.mean() < 0.95 and np.abs(real - sim).mean() > 0.01
    pairs = Pairs(Path("real"), Path("replay"), {}, {"renderer": profiled}, [f"{i:06d}" for i in range(len(depth))],
                  [{"object": "sphere"}] * len(depth), real.astype(np.float32), sim.astype(np.float32), depth, spec)
    work, _ = make_models(pairs, profiled, 4)
    assert work.profile.to_dict() == profile.to_dict() and "per-LED gains" in work.not_applicable(pairs)["led_power"]
    lens = work.predict(work.working_images(sim[:2]), None, {"vignetting": {"strength": 0.5, "exposure": 1.0}},
                        keys=[0, 1])
    assert np.isfinite(lens).all() and lens.mean() < work.working_images(sim[:2]).mean()


@pytest.mark.slow
def test_an_absorption_hidden_behind_a_units_profile_is_found(spec, scene, stub):
    """Diagnosed through the profile's camera, an absorption hidden in a replay through a
    unit's profile is ranked first, fitted and closed."""
    from scenes.profile import profile_from_dict

    profiled = _profiled(spec)
    camera, ref, depth = scene
    model = ReferenceModel(spec, profiled, 1, SourceBasis(spec, profiled, depth, film=FILM),
                           profile_from_dict(profiled["profile_data"]))
    sim, real = (np.stack([model._resized(model.image(i, p)) for i in range(len(depth))])
                 for p in ({}, {"absorption_per_m": {"value": 60.0}}))
    pairs = Pairs(Path("real"), Path("replay"), {}, {"renderer": profiled}, [f"{i:06d}" for i in range(len(depth))],
                  [{"object": "sphere"}] * len(depth), real.astype(np.float32), sim.astype(np.float32), depth, spec)
    train, heldout = split(pairs, 0.5, seed=0)
    d = Diagnosis(pairs, train, heldout, factor=4, effects=("absorption_per_m", "led_power", "camera_gains"))
    assert "led_power" in d.not_applicable
    singles = d.singles()
    ranked = [n for n, j in sorted(singles.items(), key=lambda kv: -kv[1].gain) if j.significant]
    assert ranked[0] == "absorption_per_m"
    assert singles["absorption_per_m"].fit.params["absorption_per_m"]["value"] == pytest.approx(60.0, rel=0.1)
    assert singles["absorption_per_m"].improvement["masked"]["mae"]["share"] > 0.8
