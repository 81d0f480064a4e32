"""The physically based reference as a dataset renderer: passes to a noise target, the
contact region, the plugin (settings, shared no-contact deposits, bad options), the
dataset command's renderer options and the reference command's output stem.

The stopping rule is tested analytically on a fake pass with known noise; one tiny real
render (64x48 film, 2^13 photons) checks that a contact reaches a loose target.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from pbr_tactile.estimate import Control, Estimate, contact_region, contact_rse, run_passes
from scenes.cli import main

# --- The stopping rule, analytically ------------------------------------------------------


def noisy_passes(mu: float, s: float, shape=(100, 100, 3), seed: int = 0):
    """A fake pass: mu (1 + s z) per pixel, z ~ N(0, 1), so the RSE of n passes is s / sqrt(n)."""
    rng = np.random.default_rng(seed)
    calls = []

    def one_pass(k: int) -> np.ndarray:
        calls.append(k)
        return mu * (1 + s * rng.standard_normal(shape))

    return one_pass, calls


def test_passes_stop_at_the_first_that_meets_the_target():
    # s / sqrt(n) <= 0.04 first at n = ceil((0.1 / 0.04)^2) = 7 (n = 6 gives 0.0408).
    one_pass, calls = noisy_passes(2.0, 0.1)
    est = run_passes(one_pass, spp=4, passes=2, target_rse=0.04, max_passes=16)
    assert calls == list(range(7))
    assert (est.passes, est.spp) == (7, 28)
    assert est.rse == pytest.approx(0.1 / math.sqrt(7), rel=0.02)
    assert est.rse <= 0.04


def test_passes_respect_the_fewest_and_the_cap():
    one_pass, calls = noisy_passes(2.0, 0.1)
    assert run_passes(one_pass, 1, passes=2, target_rse=0.5).passes == 2  # met at once: still 2
    one_pass, calls = noisy_passes(2.0, 0.1)
    assert run_passes(one_pass, 1, passes=3, target_rse=0.5).passes == 3
    one_pass, calls = noisy_passes(2.0, 0.1)
    capped = run_passes(one_pass, 1, passes=2, target_rse=1e-3, max_passes=5)
    assert capped.passes == 5 and capped.rse == pytest.approx(0.1 / math.sqrt(5), rel=0.02)
    one_pass, calls = noisy_passes(2.0, 0.1)
    fixed = run_passes(one_pass, 1, passes=3)  # no target: exactly the passes asked for
    assert calls == [0, 1, 2] and fixed.passes == 3 and fixed.rse is None


def test_only_the_region_counts():
    one_pass, _ = noisy_passes(2.0, 0.1)
    wild, _ = noisy_passes(2.0, 10.0, seed=1)
    region = np.zeros((100, 100), bool)
    region[:50] = True

    def half_wild(k):
        image = one_pass(k)
        image[50:] = wild(k)[50:]
        return image

    assert run_passes(half_wild, 1, passes=2, target_rse=0.04, region=region).passes == 7


@pytest.mark.parametrize("target", [0.0, -0.1, float("nan"), float("inf"), "0.05"])
def test_a_target_must_be_finite_and_positive(target):
    with pytest.raises(ValueError, match="target_rse must be a finite number > 0"):
        run_passes(lambda k: np.ones((2, 2, 3)), 1, passes=2, target_rse=target)


def test_pass_counts_are_checked():
    with pytest.raises(ValueError, match="passes must be >= 2 for a variance estimate, got 1"):
        run_passes(lambda k: np.ones((2, 2, 3)), 1, passes=1)
    with pytest.raises(ValueError, match=r"max_passes must be >= passes \(4\), got 3"):
        run_passes(lambda k: np.ones((2, 2, 3)), 1, passes=4, target_rse=0.1, max_passes=3)


def test_a_control_cancels_the_noise_it_shares():
    """Pass k = 2 + shared_k + own_k; the control's image k = 1 + shared_k, its mean 1
    known to within variance v. The estimate is 2 on average, its variance
    var(own) / n + v, and the shared noise (10x the own) is gone."""
    rng = np.random.default_rng(0)
    shape, n = (100, 100, 3), 6
    shared = 0.5 * rng.standard_normal((n, *shape))
    own = 0.05 * rng.standard_normal((n, *shape))
    control = Control(1 + shared, np.ones(shape), np.full(shape, 1e-4))
    est = run_passes(lambda k: 2 + shared[k] + own[k], 1, passes=n, control=control)
    assert est.passes == n and abs(float(np.mean(est.mean)) - 2) < 0.01
    assert float(np.mean(est.variance)) == pytest.approx(0.05**2 / n + 1e-4, rel=0.05)
    plain = run_passes(lambda k: 2 + shared[k] + own[k], 1, passes=n)
    assert float(np.mean(plain.variance)) > 50 * float(np.mean(est.variance))
    # To a target: the control's variance is part of the error judged.
    cheap = run_passes(lambda k: 2 + shared[k] + own[k], 1, passes=2, target_rse=0.015, max_passes=n,
                       control=control)
    assert cheap.passes == 4 and cheap.rse <= 0.015  # sqrt(0.05^2 / n + 1e-4) / 2 <= 0.015 first at n = 4


def test_a_control_must_cover_every_pass_and_match_the_image():
    with pytest.raises(ValueError, match="the control has 2 pass images but up to 4 passes may run"):
        run_passes(lambda k: np.ones((2, 2, 3)), 1, passes=2, target_rse=0.1, max_passes=4,
                   control=Control(np.ones((2, 2, 2, 3)), np.ones((2, 2, 3)), np.zeros((2, 2, 3))))
    with pytest.raises(ValueError, match=r"a Control needs images \(K, H, W, C\)"):
        Control(np.ones((2, 2, 3)), np.ones((2, 2, 3)), np.zeros((2, 2, 3)))


def test_contact_rse_leaves_out_unlit_pixels():
    mean = np.ones((4, 4, 3), np.float32)
    mean[0] = 0.0
    est = Estimate(mean, np.full((4, 4, 3), 0.01, np.float32), 2)
    assert contact_rse(est) == pytest.approx(0.1)
    assert math.isnan(contact_rse(est, np.zeros((4, 4), bool)))


# --- The contact region -------------------------------------------------------------------




def test_contact_region_is_the_dent_and_its_rim(camera, ref, pressed):
    from pbr_tactile.estimate import RIM_PX

    moved = np.abs(pressed - ref) > 1e-6
    region = contact_region(pressed, ref, camera)
    assert region.shape == camera.shape and region[moved].all()
    rows, cols = np.nonzero(moved)
    assert region[rows.min() - RIM_PX + 1, cols[rows == rows.min()][0]]  # the rim, above the dent
    assert not region[rows.min() - RIM_PX - 2, cols[rows == rows.min()][0]]
    half = contact_region(pressed, ref, camera, 320, 240)
    assert half.shape == (240, 320)
    assert half.sum() == pytest.approx(region.sum() / 4, rel=0.1)
    # No contact, or a contact outside the image circle: the whole circle.
    assert np.array_equal(contact_region(None, None, camera, 320, 240), camera.scaled(320, 240).mask)
    corner = ref.copy()
    corner[:5, :5] -= 1e-3
    assert np.array_equal(contact_region(corner, ref, camera), camera.mask)


# --- The plugin ---------------------------------------------------------------------------

#: Tiny settings: a 64x48 film, few photons, at most 4 passes.
OPTIONS = {"film": [64, 48], "photons": 1 << 13, "camera_spp": 2, "max_passes": 4, "no_contact_runs": 2,
           "target_rse": 0.5}


def _needs_vectorised_variant():
    pytest.importorskip("mitsuba", reason="Mitsuba 3 is not installed (pip install '.[pbr]')")
    from pbr_tactile.variant import VariantError, choose_variant

    try:
        if not choose_variant().variant().startswith(("llvm_", "cuda_")):
            pytest.skip("the photon estimator needs a vectorised variant (apt-get install libllvm19)")
    except VariantError as exc:
        pytest.skip(str(exc))


@pytest.fixture(scope="module")
def prepared(tmp_path_factory, spec, mesh, camera):
    """prepare() once on the 'driver' (its own cache), and what it shares with workers."""
    _needs_vectorised_variant()
    from pbr_tactile import plugin

    cache = str(tmp_path_factory.mktemp("driver_cache"))
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("TACTILE_SIM_CACHE", cache)
        settings = plugin.prepare(spec, mesh, camera, OPTIONS)
        shared = plugin.shared(spec, mesh, camera, OPTIONS)
    return settings, shared, cache


def test_prepare_records_every_setting(prepared):
    from pbr_tactile.effects import Effects
    from pbr_tactile.plugin import SOURCE
    from scenes.dataset import SOURCES

    settings, shared, _ = prepared
    assert SOURCE == "pbr" and SOURCE in SOURCES
    assert settings["renderer"] == "pbr" and settings["estimator"] == "photons"
    for key in ("target_rse", "max_passes", "photons", "camera_spp", "no_contact_runs", "film"):
        assert settings[key] == OPTIONS[key], key
    assert settings["kernel_radius_mm"] == 0.75 and settings["min_passes"] == 2
    assert settings["effects"] == Effects().to_dict()
    assert settings["variant"].startswith(("llvm_", "cuda_")) and settings["variant"] == shared["variant"]
    assert settings["exposure_gain"] == shared["exposure_gain"] > 0
    assert "resampled" in settings["resampling"]
    # Pilot, then per pass E_0 and G, each its flux and its tracks (inscatter "fluence"):
    # every no-contact deposit a contact may use.
    assert settings["inscatter"] == "fluence"
    assert len(shared["deposits"]) == 1 + 2 * 2 * OPTIONS["max_passes"]


def test_a_contact_reaches_a_loose_target_from_shared_deposits(monkeypatch, tmp_path, prepared, spec, mesh, camera,
                                                               ref, pressed):
    """A worker with no disk cache of its own renders from the shared deposits: it
    traces only the contact's own photons, one run per pass."""
    from pbr_tactile import photons as ph
    from pbr_tactile import plugin

    settings, shared, _ = prepared
    monkeypatch.setenv("TACTILE_SIM_CACHE", str(tmp_path / "empty"))
    traced = []
    real = ph.deposits

    def counting(*args, **kwargs):
        traced.append(args[6])
        return real(*args, **kwargs)

    monkeypatch.setattr(ph, "deposits", counting)
    renderer = plugin.make_renderer(spec, mesh, camera, ref, OPTIONS, shared=shared)
    out = renderer.render_sample(pressed)
    record = out["record"]
    print("contact sample:", record)
    assert 2 <= record["passes"] <= OPTIONS["max_passes"]
    assert record["contact_rse"] <= OPTIONS["target_rse"]
    assert record["spp"] == OPTIONS["camera_spp"] * record["passes"] and record["seconds"] > 0
    assert traced == [OPTIONS["photons"]] * record["passes"]
    assert not (tmp_path / "empty").exists()  # nothing read or written on this worker's disk
    image, linear, variance = out["image"], out["arrays"]["linear"], out["arrays"]["variance"]
    assert image.shape == linear.shape == variance.shape == (480, 640, 3)
    assert linear.dtype == variance.dtype == np.float32
    assert image.min() >= 0 and image.max() <= 1 and (variance >= 0).all()
    # the exposed linear image inside the spec's image circle, black outside it as a lens draws it
    np.testing.assert_allclose(image, np.clip(settings["exposure_gain"] * linear, 0, 1) * camera.mask[..., None],
                               atol=1e-6)
    assert image[~camera.mask].max() == 0 and image[camera.mask].max() > 0
    # The no-contact frame sets the exposure; far from the dent the contact agrees with
    # it within their errors (a z-test; the two share random numbers, so their summed
    # variances overstate the difference's and |z| runs low).
    background = renderer.no_contact
    assert background.shape == (480, 640, 3)
    film = camera.scaled(*settings["film"]).mask  # the exposure is set at the film's size
    level = np.percentile(shared["no_contact"]["mean"][film], 99.5)
    assert settings["exposure_gain"] * level == pytest.approx(0.8, rel=0.005)  # the gain has 3 digits
    frame_mean, frame_variance = (renderer.camera_size(shared["no_contact"][k]) for k in ("mean", "variance"))
    far = ~contact_region(pressed, ref, camera) & camera.mask
    z = (linear - frame_mean)[far] / np.sqrt(variance + frame_variance)[far]
    assert np.median(np.abs(z)) < 1.0
    # No contact: the no-contact frame itself, with every pass.
    untouched = renderer.render_sample(ref.astype(np.float32))
    assert untouched["record"]["passes"] == OPTIONS["max_passes"]
    np.testing.assert_array_equal(untouched["image"], background)
    assert np.array_equal(renderer.render(ref), background)


def test_the_reference_renders_with_the_camera_it_is_handed(prepared, spec, mesh, camera, ref):
    """No profile: the renderer keeps the camera it is handed (``scenes.renderers``'
    contract), here one whose image circle is not the spec's; before, it put the spec's
    own camera in its place and drew the spec's circle."""
    import dataclasses

    from pbr_tactile import plugin

    _, shared, _ = prepared
    narrow = dataclasses.replace(camera, mask_radius_px=camera.mask_radius_px * 0.7)
    ring = camera.mask & ~narrow.mask
    handed = plugin.make_renderer(spec, mesh, narrow, ref, OPTIONS, shared=shared)
    own = plugin.make_renderer(spec, mesh, camera, ref, OPTIONS, shared=shared)
    assert handed.camera is narrow and handed.spec is spec
    assert own.no_contact[ring].any() and not handed.no_contact[ring].any()
    assert np.array_equal(handed.no_contact[narrow.mask], own.no_contact[narrow.mask])


def test_resuming_with_other_settings_is_refused(monkeypatch, tmp_path, prepared, spec, mesh, camera):
    from pbr_tactile import plugin
    from scenes.dataset import DatasetError, DatasetWriter

    settings, _, cache = prepared

    def no_render(*args, **kwargs):
        raise AssertionError("the no-contact frame should come from the cache")

    # The frame is cached per pass cap, not per target: this prepare renders nothing.
    monkeypatch.setenv("TACTILE_SIM_CACHE", cache)
    monkeypatch.setattr(plugin, "reference", no_render)
    other = plugin.prepare(spec, mesh, camera, {**OPTIONS, "target_rse": 0.2})
    assert other == {**settings, "target_rse": 0.2}
    meta = {"source": plugin.SOURCE, "sensor": {"name": "geltip"}, "protocol": {"name": "base"}}
    DatasetWriter(tmp_path, {**meta, "renderer": settings})
    DatasetWriter(tmp_path, {**meta, "renderer": settings})  # the same settings: it resumes
    with pytest.raises(DatasetError, match="different renderer"):
        DatasetWriter(tmp_path, {**meta, "renderer": other})


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"field": "plane"}, "the pbr renderer takes no option field; its options are target_rse"),
        ({"target_rse": 0}, "option target_rse must be a finite number > 0, got 0"),
        ({"target_rse": -0.1}, "option target_rse must be a finite number > 0, got -0.1"),
        ({"target_rse": float("nan")}, "option target_rse must be a finite number > 0, got nan"),
        ({"max_passes": 1}, "option max_passes must be a whole number >= 2, got 1"),
        ({"max_passes": 2.5}, "option max_passes must be a whole number >= 2, got 2.5"),
        ({"photons": 0}, "option photons must be a whole number >= 1, got 0"),
        ({"camera_spp": True}, "option camera_spp must be a whole number >= 1, got True"),
        ({"kernel_radius_mm": -1}, "option kernel_radius_mm must be a finite number >= 0, got -1"),
        ({"no_contact_runs": -1}, "option no_contact_runs must be a whole number >= 0, got -1"),
        ({"effects": ["banana=1"]}, "option effects: effect setting 'banana=1': expected NAME=VALUE"),
        ({"effects": ["vignetting=2"]}, r"option effects: Effects.vignetting must be in \[0, 1\], got 2.0"),
        ({"effects": "vignetting=0.2"}, "option effects must be a list of NAME=VALUE strings"),
        ({"effects": ["coating_roughness=0"]}, r"option effects: Effects.coating_roughness must be in \[0.001, 1\], got 0.0"),
        ({"estimator": "volpath", "effects": ["contact_shadow=off"]}, "contact_shadow=false needs estimator photons"),
        ({"estimator": "magic"}, "option estimator must be 'photons' or 'volpath', got 'magic'"),
        ({"film": [320, 200]}, r"option film must be \[width, height\] .* the camera's aspect .* got 320x200"),
        ({"film": [1280, 960]}, "at most 640x480 .* got 1280x960"),
        ({"film": [0, 0]}, "got 0x0"),
        ({"film": "320x240"}, r"got '320x240'"),
        ({"film": [320.0, 240.0]}, r"got \[320.0, 240.0\]"),
        ({"seed": -1}, "option seed must be a whole number >= 0, got -1"),
        ({"led_power": 2.0}, "option led_power must be a list of each LED's radiance scale, got 2.0"),
        ({"led_power": [1.0, 2.0]}, r"led_power must be a finite radiance scale > 0, got \[1.0, 2.0\]; or one per LED \(3\)"),
        ({"led_power": [1.0, 0.0, 1.0]}, "led_power must be a finite radiance scale > 0"),
        ({"led_power": [1.0, 1.0, 1.0], "profile": "unit/profile.toml"}, "option led_power cannot go with a profile"),
    ],
)
def test_bad_options_are_refused_before_any_work(options, message, spec, mesh, camera, monkeypatch):
    from pbr_tactile import plugin

    def no_render(*args, **kwargs):
        raise AssertionError("validation comes first")

    monkeypatch.setattr(plugin, "reference", no_render)
    with pytest.raises(ValueError, match=message):
        plugin.prepare(spec, mesh, camera, options)
    with pytest.raises(ValueError, match=message):
        plugin.make_renderer(spec, mesh, camera, None, options)


# --- The dataset command's renderer options -------------------------------------------------


@pytest.fixture
def captured(monkeypatch):
    """Replace dataset generation with a stub that keeps the renderer and its options."""
    import scenes.generate

    calls = []

    def generate(root, spec, protocol, renderer, options, **kwargs):
        calls.append((renderer, options))
        return {"samples": 0, "new": 0, "seconds": 0.0, "workers": 1}

    monkeypatch.setattr(scenes.generate, "generate", generate)
    return calls


DATASET = ["dataset", "--objects", "sphere", "--limit", "1", "--out"]


def test_pbr_options_are_passed_only_when_given(tmp_path, captured):
    """The command line looks the renderer up by name and passes the plugin."""
    import pbr_tactile.plugin
    import phong_reference.plugin

    assert main([*DATASET, str(tmp_path), "--renderer", "pbr", "--target-rse", "0.1", "--max-passes", "8",
                 "--effect", "vignetting=0.2", "--effect", "scattering_per_m=0", "--estimator", "photons",
                 "--photons", "4096", "--camera-spp", "4", "--kernel-radius-mm", "0.5", "--no-contact-runs", "2",
                 "--film", "320x240"]) == 0
    assert captured[-1] == (pbr_tactile.plugin, {"target_rse": 0.1, "max_passes": 8, "effects": ["vignetting=0.2",
                            "scattering_per_m=0"], "estimator": "photons", "photons": 4096, "camera_spp": 4,
                            "kernel_radius_mm": 0.5, "no_contact_runs": 2, "film": [320, 240]})
    assert main([*DATASET, str(tmp_path)]) == 0
    assert captured[-1] == (phong_reference.plugin, {})  # the phong renderer's defaults fill in
    assert main([*DATASET, str(tmp_path), "--field", "linear", "--rectify"]) == 0
    assert captured[-1] == (phong_reference.plugin, {"field": "linear", "rectify": True})


def test_film_must_be_w_x_h(tmp_path, captured, capsys):
    with pytest.raises(SystemExit):
        main([*DATASET, str(tmp_path), "--renderer", "pbr", "--film", "320"])
    assert "expected WxH in pixels, e.g. 320x240; got '320'" in capsys.readouterr().err


def test_phong_refuses_pbr_options(spec, mesh, camera):
    from phong_reference.plugin import prepare

    with pytest.raises(ValueError, match="the phong renderer takes no option effects, target_rse; its options are "
                                         "field, background, rectify"):
        prepare(spec, mesh, camera, {"target_rse": 0.1, "effects": []})


# --- The reference command's output stem --------------------------------------------------


def test_output_paths_keep_the_whole_stem():
    from pathlib import Path

    from pbr_tactile.cli import output_paths

    assert output_paths("out/s_0.5") == {"linear": Path("out/s_0.5.npy"), "variance": Path("out/s_0.5_variance.npy"),
                                         "image": Path("out/s_0.5.png")}
    assert output_paths("a.b.c")["image"] == Path("a.b.c.png")
    # A stem naming one of the outputs: all three beside it, not frame.npy.npy.
    assert output_paths("out/frame.npy") == output_paths("out/frame") == output_paths("out/frame.PNG")


def test_reference_writes_files_named_by_a_dotted_stem(tmp_path, monkeypatch, camera, ref):
    import pbr_tactile.render

    def reference(depth, ref_depth, *args, **kwargs):
        return Estimate(np.ones((6, 8, 3), np.float32), np.full((6, 8, 3), 1e-4, np.float32), 4, 2)

    monkeypatch.setattr(pbr_tactile.render, "reference", reference)
    np.save(tmp_path / "depth.npy", ref)
    assert main(["reference", str(tmp_path / "depth.npy"), "--ref-depth", str(tmp_path / "depth.npy"),
                 "--out", str(tmp_path / "out" / "s_0.5")]) == 0
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["s_0.5.npy", "s_0.5.png", "s_0.5_variance.npy"]
    assert np.load(tmp_path / "out" / "s_0.5_variance.npy").shape == (6, 8, 3)


@pytest.mark.slow
def test_a_pbr_dataset_end_to_end(tmp_path, spec, mesh, monkeypatch):
    """tactile-sim dataset --renderer pbr on two MuJoCo taps: source "pbr", the linear image
    and its variance beside each PNG, the achieved noise in each sample's line, resumable."""
    _needs_vectorised_variant()
    from scenes.gl import GLPlatformError, choose_gl

    try:
        choose_gl()
    except GLPlatformError as exc:
        pytest.skip(str(exc))
    pytest.importorskip("mujoco")
    from dataclasses import replace

    from pbr_tactile import plugin
    from scenes.dataset import load_sample, read_meta, read_samples
    from scenes.generate import generate
    from scenes.protocol import base_protocol

    protocol = base_protocol(spec, mesh, ["sphere"])
    protocol = replace(protocol, taps=protocol.taps[1:3])
    out = tmp_path / "pbr"
    summary = generate(out, spec, protocol, plugin, OPTIONS, workers=1, progress=False)
    assert summary["samples"] == 2
    meta = read_meta(out)
    assert meta["source"] == "pbr" and meta["renderer"]["renderer"] == "pbr"
    for record in read_samples(out):
        image, depth = load_sample(out, record, (480, 640))
        linear, variance = np.load(out / record["linear"]), np.load(out / record["variance"])
        assert linear.shape == variance.shape == image.shape and (variance >= 0).all()
        assert record["contact_rse"] <= OPTIONS["target_rse"] and record["passes"] >= 2
        assert record["linear"] == f"linear/{record['id']}.npy"
    assert (out / "background.png").exists()
    again = generate(out, spec, protocol, plugin, OPTIONS, workers=1, progress=False)
    assert again["new"] == 0
