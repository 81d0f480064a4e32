"""The light-field study against the physically based reference (studies.pbr_field_comparison).

The quick run needs Mitsuba with a vectorised (llvm_ or cuda_) variant, and skips saying
why when there is none; the published-map test needs the reference data. The rest is
analytic and always runs.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from phong_reference.bake import METHODS
from studies import pbr_field_comparison as study


@pytest.fixture(scope="module")
def vectorised_mitsuba():
    pytest.importorskip("mitsuba", reason="Mitsuba 3 is not installed (pip install '.[pbr]')")
    from pbr_tactile.variant import VariantError, choose_variant

    try:
        mi = choose_variant()
    except VariantError as exc:
        pytest.skip(f"no usable Mitsuba variant: {exc}")
    if not mi.variant().startswith(("llvm_", "cuda_")):
        pytest.skip(f"the photon estimator needs an llvm_ or cuda_ variant, got {mi.variant()} "
                    "(apt-get install libllvm19)")
    return mi.variant()


@pytest.fixture(scope="module")
def quick(vectorised_mitsuba, tmp_path_factory):
    out = tmp_path_factory.mktemp("pbr_study")
    return out, study.run(out, study.QUICK, study.QUICK_CONTACTS, reference_dir=None)


@pytest.mark.slow
def test_quick_run_writes_a_complete_table_with_bracketing_intervals(quick):
    out, results = quick
    assert set(results["table"]) == set(METHODS)
    assert results["best"] in METHODS
    for method, row in results["table"].items():
        for kind in study.KINDS:
            for metric in study.METRICS:
                c = row[kind][metric]
                assert len(c["values"]) == len(study.QUICK_CONTACTS)
                assert np.isfinite([c["mean"], c["ci_low"], c["ci_high"], *c["values"]]).all(), (method, kind, c)
                assert c["ci_low"] <= c["mean"] <= c["ci_high"], (method, kind, metric, c)
    for kind in study.CHANGE_KINDS:
        for c in results["baseline_no_change"][kind].values():
            assert c["ci_low"] <= c["mean"] <= c["ci_high"]
    # Every calibration gain is a units map: never negative.
    assert all(np.min(c["gain"]) >= 0 for c in results["calibration"].values())
    for row in results["table"].values():
        r = row["contact"][study.CORRELATION]
        assert -1 <= r["ci_low"] <= r["mean"] <= r["ci_high"] <= 1
    assert results["contact_names"] == list(study.QUICK_CONTACTS)
    assert 0 <= results["unreliable_share"] < 1
    for name in study.QUICK_CONTACTS:
        assert results["contacts"][name]["max_displacement_m"] > 0.5e-3
        assert (out / f"grid_{name}.png").stat().st_size > 0
    assert (out / "metrics.png").stat().st_size > 0
    summary = (out / "summary.md").read_text()
    assert all(f"| {m}" in summary for m in METHODS) and "Conclusion" in summary
    assert json.loads((out / study.JSON_NAME).read_text())["best"] == results["best"]


@pytest.mark.slow
def test_references_are_cached_atomically_and_read_back(quick, spec, mesh, camera):
    from scenes.camera import reference_depth

    out, first = quick
    assert not any(first["reference_cached"].values())
    folder = out / study.CACHE_FOLDER
    cache = sorted(folder.glob("*.npy"))
    assert len(cache) == 1 + len(study.QUICK_CONTACTS)
    assert not list(folder.glob("*.tmp")) and not list(folder.glob(".*"))  # written atomically
    assert all(np.load(p).shape == (2, study.QUICK.height, study.QUICK.width, 3) for p in cache)
    ref = reference_depth(mesh, camera)[0]
    mean, variance, hit = study.reference_frame(study.NO_CONTACT, None, ref, mesh, spec, camera, study.QUICK, folder)
    assert hit  # keyed by name, resolution, photons and the rest: the same frame is not rendered again
    stored = np.load(next(p for p in cache if p.name.startswith(study.NO_CONTACT)))
    assert np.array_equal(mean, stored[0]) and np.array_equal(variance, stored[1])


def test_published_maps_are_moved_onto_our_membrane_and_the_deep_spheres_refused(reference_dir, spec, mesh, camera):
    from pbr_tactile.membrane import ElastomerBuilder
    from scenes.camera import reference_depth

    ref = reference_depth(mesh, camera)[0]
    maps = study.published_contacts(reference_dir, ref)
    assert list(maps) == list(study.PUBLISHED)
    for depth in maps.values():
        assert depth.shape == camera.shape and depth.dtype == np.float32
        assert np.all(depth <= ref) and np.any(depth < ref)
    build = ElastomerBuilder(mesh, spec, camera, edge=0.5e-3)
    # Map 0 (the textured height field) folded the published model over; the layer drapes it.
    assert study.refusal(maps["published_0"], ref, build) is None
    # A published sphere reaches ~8 mm along the camera ray: through the glass.
    assert "through the glass core" in study.refusal(maps["published_1"], ref, build)


def test_calibration_recovers_a_known_affine_map_and_never_inverts():
    rng = np.random.default_rng(3)
    mask = np.ones((12, 16), bool)
    mask[0] = False
    fast = rng.uniform(0, 1, (3, 12, 16, 3))
    gain, offset = np.array([0.5, 2.0, 1.0]), np.array([0.1, -0.2, 0.0])
    ref = gain * fast + offset
    ref[:, 0] = 99.0  # outside the mask: ignored
    g, o = study.fit_affine(fast, ref, mask)
    assert np.allclose(g, gain) and np.allclose(o, offset)
    g, _ = study.fit_affine(fast, -fast, mask)
    assert np.allclose(g, 0.0, atol=1e-9)  # anticorrelated: predicts no change, never an inverted one
    gains, offsets = study.leave_one_out_calibration(fast, gain * fast + offset, mask)
    assert gains.shape == (2, 3) and np.allclose(gains, gain) and np.allclose(offsets, offset)
    change = fast[1:] - fast[:1]
    assert np.allclose(study.fit_gain(change, 3.0 * change, mask), 3.0)
    assert np.allclose(study.fit_gain(change, -change, mask), 0.0)  # never inverted
    assert np.allclose(study.fit_gain(np.zeros_like(change), change, mask), 0.0)  # no signal, no gain


def test_reliable_pixels():
    mean = np.full((2, 8, 8, 3), 0.5)
    variance = np.full_like(mean, 1e-4)
    variance[1, 3, 4, 0] = 100.0  # one spike in one frame and channel
    ok = study.reliable_pixels(mean, variance, np.ones((8, 8), bool))
    assert not ok[3, 4] and ok.sum() == 63


def test_change_metrics_name_the_metrics_and_area_averaging():
    # the metrics are scenes.image_stats.image_metrics' (tests/test_image_stats.py), named
    # as this study's JSON names them
    rng = np.random.default_rng(4)
    x = rng.uniform(0, 1, (24, 32, 3))
    mask = np.ones((24, 32), bool)
    m = study.change_metrics(x, x + 0.1, mask, mask, mask)
    assert set(m) == set(study.CHANGE_KINDS) and all(tuple(m[k]) == study.METRICS for k in m)
    assert m["change"]["mae"] == pytest.approx(0.1)
    assert m["change"]["psnr_db"] == pytest.approx(20.0 + 20 * np.log10(np.ptp(x)))  # data range: the span
    small = study.downsample(np.repeat(np.repeat(x, 4, axis=0), 4, axis=1), (24, 32))
    assert np.allclose(small, x)


def test_bootstrap_interval_brackets_the_mean():
    c = study.bootstrap_mean([0.1, 0.3, 0.2, 0.5], seed=0)
    assert c["ci_low"] <= c["mean"] <= c["ci_high"] and c["ci_low"] < c["ci_high"]
    assert c == study.bootstrap_mean([0.1, 0.3, 0.2, 0.5], seed=0)  # seeded
    same = study.bootstrap_mean([0.2, 0.2], seed=0)
    assert same["ci_low"] == same["mean"] == same["ci_high"] == 0.2


def test_validators_refuse_bad_input(tmp_path, camera):
    with pytest.raises(ValueError, match="width x height must divide"):
        study.check_settings(study.Settings(width=100, height=48), camera)
    with pytest.raises(ValueError, match="passes must be >= 2"):
        study.check_settings(study.Settings(passes=1), camera)
    with pytest.raises(ValueError, match="spp >= passes"):
        study.check_settings(study.Settings(spp=2, passes=4), camera)
    with pytest.raises(ValueError, match="contacts must be >= 2 distinct names"):
        study.run(tmp_path, study.QUICK, ("sphere_tip", "teapot"))
    with pytest.raises(ValueError, match="contacts must be >= 2 distinct names"):
        study.run(tmp_path, study.QUICK, ("sphere_tip",))
    with pytest.raises(ValueError, match="need the published data"):
        study.run(tmp_path, study.QUICK, ("sphere_tip", "published_1"), reference_dir=None)
    with pytest.raises(ValueError, match="values must be >= 2 finite numbers"):
        study.bootstrap_mean([0.1], seed=0)
    with pytest.raises(ValueError, match="values must be >= 2 finite numbers"):
        study.bootstrap_mean([0.1, np.nan], seed=0)
    with pytest.raises(ValueError, match="at least 2 contacts"):
        study.leave_one_out_calibration(np.zeros((2, 4, 4, 3)), np.zeros((2, 4, 4, 3)), np.ones((4, 4), bool))
    with pytest.raises(ValueError, match="change_fast and change_ref must be"):
        study.fit_gain(np.zeros((4, 4, 3)), np.zeros((4, 5, 3)), np.ones((4, 4), bool))
    with pytest.raises(ValueError, match="black inside the mask"):
        study.reliable_pixels(np.zeros((1, 4, 4, 3)), np.zeros((1, 4, 4, 3)), np.ones((4, 4), bool))
    with pytest.raises(ValueError, match="fast and ref must be"):
        study.fit_affine(np.zeros((4, 4, 3)), np.zeros((4, 5, 3)), np.ones((4, 4), bool))
    with pytest.raises(ValueError, match="integer multiple"):
        study.downsample(np.zeros((10, 10, 3)), (3, 3))
    with pytest.raises(ValueError, match="analytic contacts must be among"):
        study.analytic_contacts(None, camera, None, ("teapot",))


def test_the_study_runs_on_any_shape_but_the_published_maps_are_the_geltips(tmp_path):
    from pathlib import Path

    from scenes.spec_read import load_spec

    thumb = load_spec(Path(__file__).parents[1] / "scenes" / "sensors" / "thumb.toml")
    with pytest.raises(ValueError, match="published depth maps are the GelTip's"):
        study.run(tmp_path, study.QUICK, ("sphere_tip", "published_0"), None, thumb)


def test_region_errors_score_each_class_against_predicting_no_change():
    rng = np.random.default_rng(6)
    K, h, w = 4, 6, 8
    ref = rng.normal(size=(K, h, w, 3))
    regions = np.full((h, w), "convex")
    regions[:, 4:] = "saddle"
    regions[0] = "flat"  # seen by one contact alone: left out
    pixels = np.ones((K, h, w), bool)
    pixels[1:, 0] = False
    perfect = study.region_errors(ref, ref, pixels, regions, seed=0)
    assert set(perfect) == {"convex", "saddle"}
    assert all(r["ratio"] == r["ci_low"] == r["ci_high"] == 0.0 and r["contacts"] == K for r in perfect.values())
    none = study.region_errors(np.zeros_like(ref), ref, pixels, regions, seed=0)
    assert all(r["ratio"] == pytest.approx(1.0) for r in none.values())
    # Right on the convex pixels, doubled (error = signal) on the saddle ones.
    pred = np.where((regions == "saddle")[None, ..., None], 2 * ref, ref)
    mixed = study.region_errors(pred, ref, pixels, regions, seed=0)
    assert mixed["convex"]["ratio"] == 0.0 and mixed["saddle"]["ratio"] == pytest.approx(1.0)
    assert mixed["saddle"]["pixels"] == K * (h - 1) * 4
    # Noisy predictions: the interval brackets the ratio.
    noisy = study.region_errors(ref + rng.normal(scale=0.5, size=ref.shape), ref, pixels, regions, seed=0)
    assert all(r["ci_low"] <= r["ratio"] <= r["ci_high"] and r["ci_low"] < r["ci_high"] for r in noisy.values())
    with pytest.raises(ValueError, match="must agree"):
        study.region_errors(ref, ref, pixels[:, :, :4], regions, seed=0)


def test_contact_regions_and_failures_name_the_classes_where_a_field_does_no_better_than_no_change():
    per_contact = {"good": [{"change": {"mae": 0.1 + 0.01 * k}} for k in range(5)],
                   "bad": [{"change": {"mae": 0.5 + 0.01 * k}} for k in range(5)]}
    no_change = [{"change": {"mae": 0.4}} for _ in range(5)]
    table = study.contact_region_table(per_contact, no_change, ["saddle"] * 3 + ["convex", "flat"], seed=0)
    assert list(table) == ["saddle"]  # one contact per other class: left out
    assert table["saddle"]["contacts"] == 3
    assert table["saddle"]["good"]["no_change_minus_field"]["ci_low"] > 0
    assert table["saddle"]["bad"]["no_change_minus_field"]["ci_high"] < 0
    ratio = lambda r, lo, hi: {"ratio": r, "ci_low": lo, "ci_high": hi, "pixels": 10, "contacts": 3}  # noqa: E731
    results = {"pixel_regions": {"ratio": {"good": {"saddle": ratio(0.5, 0.4, 0.6), "convex": ratio(0.9, 0.7, 1.1)},
                                           "bad": {"saddle": ratio(1.2, 1.0, 1.5)}}}}
    assert study.failures(results) == {"good": {"fails": [], "tracks": ["saddle"], "unclear": ["convex"]},
                                       "bad": {"fails": ["saddle"], "tracks": [], "unclear": []}}


def test_surface_taps_spread_over_each_class_of_the_paw():
    from pathlib import Path

    from scenes.curvature import classify, principal_curvatures
    from scenes.geometry import membrane_mesh
    from scenes.spec_read import load_spec

    paw = load_spec(Path(__file__).parents[1] / "scenes" / "sensors" / "paw.toml")
    mesh = membrane_mesh(paw)
    taps = study.surface_taps(paw, mesh, per_class=3, seed=0)
    assert taps == study.surface_taps(paw, mesh, per_class=3, seed=0)  # seeded
    named = [name.split("_")[1] for name in taps]
    points = np.array([t.point for t in taps.values()])
    assert list(classify(principal_curvatures(mesh, points))) == named  # each tap sits on its class
    assert {"convex", "cylindrical", "saddle"} <= set(named) and max(named.count(c) for c in named) == 3
    saddles = points[[c == "saddle" for c in named]]
    # Farthest-point sampling: the saddles are the valleys between the toes and the waist below them.
    assert np.ptp(saddles[:, 2]) > 0.015
    assert all(t.replica == 0 and t.object in name for name, t in taps.items())
    with pytest.raises(ValueError, match="per_class must be an integer >= 1"):
        study.surface_taps(paw, mesh, per_class=0)
    # Captured on the rig and moved onto the ray-cast D_ref: untouched pixels are D_ref
    # exactly (the rig's own depth differs from it by up to ~0.1 mm), the dent is the tap's.
    from scenes.camera import Camera, reference_depth

    ref = reference_depth(mesh, Camera.from_spec(paw))[0]
    name = next(n for n in taps if n.startswith("surface_saddle"))
    depth = study.rig_contacts(paw, mesh, {name: taps[name]}, ref)[name]
    dent = ref - depth
    assert depth.dtype == np.float32 and (dent >= 0).all()
    assert 100 < (dent > 0).sum() < 0.2 * dent.size  # a contact, not the whole membrane
    assert 1.5e-3 < dent.max() < 6e-3  # 2 mm along the normal, more along an oblique ray
