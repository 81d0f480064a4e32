"""scenes.image_stats: image metrics, agreement over pixels, the contact strength, the
Monte Carlo noise floor and the intervals of a mean, analytically."""

from __future__ import annotations

import math

import numpy as np
import pytest

from scenes import image_stats as st

#: Student's t quantile t_0.975,2 (a printed table's value).
T_975_2 = 4.302653


# --- image metrics --------------------------------------------------------------------------

def test_masked_metrics_of_a_constant_offset():
    rng = np.random.default_rng(0)
    x = rng.uniform(0, 0.8, (20, 24, 3))
    region = np.zeros((20, 24), bool)
    region[5:15, 4:20] = True
    y = x.copy()
    y[region] += 0.1  # outside the region the images agree
    m = st.masked_metrics(x, y, region, 1.0)
    assert m["mae"] == pytest.approx(0.1) and m["psnr"] == pytest.approx(20.0)  # 10 log10(1 / 0.01)
    assert math.isnan(m["ssim"])  # no SSIM map given
    whole = st.masked_metrics(x, y, None, 1.0)
    assert whole["mae"] == pytest.approx(0.1 * region.mean())
    # PSNR scales with the data range: 10 log10(range^2 / MSE)
    assert st.masked_metrics(x, y, region, 2.0)["psnr"] == pytest.approx(20.0 + 20 * math.log10(2.0))
    assert st.masked_metrics(x, x, region, 1.0)["psnr"] == math.inf  # identical: no warning, infinite


def test_ssim_map_of_an_image_with_itself_is_one():
    x = np.random.default_rng(1).uniform(0, 1, (16, 16, 3))
    smap = st.ssim_map(x, x, 1.0)
    assert smap.shape == x.shape and np.allclose(smap, 1.0)
    assert st.masked_metrics(x, x, np.ones((16, 16), bool), 1.0, smap)["ssim"] == pytest.approx(1.0)


def test_image_metrics_of_identical_and_offset_images():
    rng = np.random.default_rng(4)
    x = rng.uniform(0, 1, (24, 32, 3))
    mask = np.ones((24, 32), bool)
    m = st.image_metrics(x, x, mask, 1.0)
    assert m["mae"] == 0 and m["ssim"] == pytest.approx(1.0) and m["psnr"] == math.inf
    m = st.image_metrics(x, x + 0.1, mask, 1.0)
    assert m["mae"] == pytest.approx(0.1) and m["psnr"] == pytest.approx(20.0)
    # outside the mask both are set to zero: a difference there does not count
    inner = np.zeros_like(mask)
    inner[4:20, 4:28] = True
    y = np.where(inner[..., None], x, 0.9)
    assert st.image_metrics(x, y, inner, 1.0)["mae"] == 0.0


def test_metrics_of_known_images(camera):
    a = np.full((2, 480, 640, 3), 0.5, np.float32)
    b = a + 0.1
    m = st.per_sample(a, b, camera.mask)
    assert np.allclose(m["full"]["mae"], 0.1, atol=1e-6)
    assert np.allclose(m["masked"]["mae"], 0.1, atol=1e-6)
    assert np.allclose(m["full"]["psnr"], 20.0, atol=1e-3)  # 10 log10(1 / 0.01)
    same = st.per_sample(a, a, camera.mask)
    assert np.allclose(same["full"]["ssim"], 1.0) and np.all(same["full"]["psnr"] == st.PSNR_CAP_DB)
    quick = st.per_sample(a, b, camera.mask, ssim=False)
    assert np.isnan(quick["masked"]["ssim"]).all() and np.allclose(quick["masked"]["mae"], 0.1, atol=1e-6)


def test_metrics_per_region_measure_only_their_pixels(camera):
    a = np.full((2, 480, 640, 3), 0.5, np.float32)
    b = a.copy()
    top = np.zeros(camera.shape, bool)
    top[:240] = True
    b[:, :240] += 0.1
    b[:, 240:] += 0.3
    m = st.per_sample(a, b, camera.mask, regions={"top": top, "bottom": ~top})
    assert np.allclose(m["top"]["mae"], 0.1, atol=1e-6) and np.allclose(m["bottom"]["mae"], 0.3, atol=1e-6)
    assert np.allclose(m["top"]["psnr"], 20.0, atol=1e-3)
    assert 0.1 < m["masked"]["mae"][0] < 0.3
    contact = np.zeros((2,) + camera.shape, bool)
    contact[0] = top & camera.mask  # sample 1's region stays empty
    m = st.per_sample(a, b, camera.mask, contact=contact, ssim=False)
    assert m["contact"]["mae"][0] == pytest.approx(0.1, abs=1e-6) and np.isnan(m["contact"]["mae"][1])
    with pytest.raises(ValueError, match="region 'masked'"):
        st.per_sample(a, b, camera.mask, regions={"masked": top})
    with pytest.raises(ValueError, match="with pixels inside"):
        st.per_sample(a, b, camera.mask, regions={"outside": ~camera.mask})
    with pytest.raises(ValueError, match="regions or areas"):
        st.per_sample(a, b, camera.mask, regions={"top": top}, areas=np.ones((2,) + camera.shape, bool))


@pytest.mark.parametrize("call, match", [
    (lambda: st.ssim_map(np.zeros((8, 8, 3)), np.zeros((8, 9, 3)), 1.0), "expected and actual must be"),
    (lambda: st.ssim_map(np.zeros((8, 8, 3)), np.zeros((8, 8, 3)), 0.0), "data_range must be > 0"),
    (lambda: st.masked_metrics(np.zeros((8, 8, 3)), np.zeros((8, 8, 3)), np.ones((8, 9), bool), 1.0),
     r"with region \(H, W\)"),
    (lambda: st.image_metrics(np.zeros((8, 8, 3)), np.zeros((8, 8, 3)), np.ones((8, 8), bool), 1.0,
                              np.zeros((8, 8), bool)), "region must hold"),
    (lambda: st.image_metrics(np.zeros((8, 8, 3)), np.zeros((8, 8, 3)), np.ones((8, 8), bool), 0.0),
     "data_range must be > 0"),
    (lambda: st.image_metrics(np.zeros((8, 8, 3)), np.zeros((8, 8, 3)), np.ones((8, 7), bool), 1.0),
     "expected and actual must be"),
    (lambda: st.per_sample(np.zeros((2, 8, 8, 3)), np.zeros((2, 8, 8, 2)), np.ones((8, 8), bool)),
     "real and predicted images differ in shape"),
    (lambda: st.per_sample(np.zeros((2, 8, 8, 3)), np.zeros((2, 8, 8, 3)), np.ones((8, 7), bool)),
     r"images must be \(N, H, W, 3\) with an \(H, W\) mask"),
    (lambda: st.per_sample(np.zeros((2, 8, 8, 3)), np.zeros((2, 8, 8, 3)), np.ones((8, 8), bool),
                           contact=np.ones((2, 8, 8))), "contact must be"),
])
def test_image_metrics_refuse_bad_input(call, match):
    with pytest.raises(ValueError, match=match):
        call()


# --- agreement over pixels ---------------------------------------------------------------------

def test_r2_of_a_perfect_and_of_the_mean_prediction():
    rng = np.random.default_rng(2)
    real = rng.uniform(0, 1, (10, 12))
    pixels = rng.uniform(size=(10, 12)) > 0.3
    assert st.r2(real, real, pixels) == 1.0
    assert st.r2(np.full_like(real, real[pixels].mean()), real, pixels) == pytest.approx(0.0, abs=1e-12)
    assert math.isnan(st.r2(real, np.ones_like(real), pixels))  # nothing to explain
    # weights: a pixel weighted twice counts as two; weight 0 leaves it out
    weights = np.where(pixels, 1.0, 0.0)
    assert st.r2(0.9 * real, real, np.ones_like(pixels), weights) == st.r2(0.9 * real, real, pixels)
    assert math.isnan(st.r2(real, real, pixels, np.zeros((10, 12))))


def test_pearson_of_linear_and_constant_arrays():
    a = np.random.default_rng(5).normal(size=100)
    assert st.pearson(a, 2 * a + 1) == pytest.approx(1.0)
    assert st.pearson(a, -a) == pytest.approx(-1.0)
    assert st.pearson(np.zeros(100), a) == 0.0  # a field that predicts no change
    assert st.pearson(np.zeros(100), a, constant=None) is None  # reported as undefined (the tiles)


def test_agreement_refuses_bad_input():
    with pytest.raises(ValueError, match="same number"):
        st.pearson(np.zeros(3), np.zeros(4))
    with pytest.raises(ValueError, match="pred and real must be one shape"):
        st.r2(np.zeros((4, 4)), np.zeros((4, 5)), np.ones((4, 5), bool))
    with pytest.raises(ValueError, match="pixels a bool mask"):
        st.r2(np.zeros((4, 4)), np.zeros((4, 4)), np.ones((4, 4)))
    with pytest.raises(ValueError, match="weights must be shaped like pixels"):
        st.r2(np.zeros((4, 4)), np.zeros((4, 4)), np.ones((4, 4), bool), np.ones(16))


# --- contact strength ------------------------------------------------------------------------------

def test_contact_strength_is_the_mean_change_over_the_region():
    rng = np.random.default_rng(0)
    no_contact = rng.uniform(0.2, 0.6, (12, 16, 3))
    regions = np.zeros((3, 12, 16), bool)
    regions[0, 2:5, 3:9] = True
    regions[1, 6:, :4] = True  # region 2 stays empty
    images = np.repeat(no_contact[None], 3, axis=0)
    images[0][regions[0]] += [0.3, -0.1, 0.2]  # |change| averaged over channels: 0.2
    images[1][regions[1]] -= 0.05
    images[0, 0, 0] += 0.5  # outside every region: not counted
    out = st.contact_strength(images, no_contact, regions)
    assert out[0] == pytest.approx(0.2) and out[1] == pytest.approx(0.05) and np.isnan(out[2])
    # one no-contact frame per image, and one region for all
    per_image = st.contact_strength(images, np.repeat(no_contact[None], 3, axis=0), regions[0])
    assert per_image[0] == pytest.approx(0.2) and per_image[1] == 0.0
    # simulated over real: a simulation twice as strong has the ratio 2
    sim = no_contact + 2 * (images - no_contact)
    ratio = st.contact_strength(sim, no_contact, regions) / out
    assert ratio[:2] == pytest.approx([2.0, 2.0])


@pytest.mark.parametrize("args, match", [
    ((np.zeros((2, 4, 4)), np.zeros((4, 4, 3)), np.ones((4, 4), bool)), r"images must be \(N, H, W, 3\)"),
    ((np.zeros((2, 4, 4, 3)), np.zeros((4, 5, 3)), np.ones((4, 4), bool)), r"no_contact must be \(H, W, 3\) or"),
    ((np.zeros((2, 4, 4, 3)), np.zeros((4, 4, 3)), np.ones((3, 4, 4), bool)), r"regions must be \(N, H, W\) or"),
])
def test_contact_strength_refuses_bad_shapes(args, match):
    with pytest.raises(ValueError, match=match):
        st.contact_strength(*args)


def test_contact_contrast_splits_the_strength_into_level_and_relative_change():
    no_contact = np.full((6, 8, 3), [0.2, 0.4, 0.5])
    regions = np.zeros((2, 6, 8), bool)
    regions[0, 1:3, 2:6] = True  # region 1 stays empty
    images = np.repeat(no_contact[None], 2, axis=0)
    images[0][regions[0]] += [0.1, -0.1, 0.0]
    got = st.contact_contrast(images, no_contact, regions)
    np.testing.assert_allclose(got["level"][0], [0.2, 0.4, 0.5])
    np.testing.assert_allclose(got["change"][0], [0.1, 0.1, 0.0], atol=1e-12)
    np.testing.assert_allclose(got["relative"][0], [0.5, 0.25, 0.0], atol=1e-12)
    assert np.isnan(got["level"][1]).all() and np.isnan(got["relative"][1]).all()
    # the strength is the channels' mean change, and a camera that doubles every value
    # doubles the level, not the relative change
    assert st.contact_strength(images, no_contact, regions)[0] == pytest.approx(0.2 / 3)
    doubled = st.contact_contrast(2 * images, 2 * no_contact, regions)
    np.testing.assert_allclose(doubled["relative"][0], got["relative"][0], atol=1e-12)
    # an offset (a pedestal) raises the level and dilutes the relative change
    lifted = st.contact_contrast(images + 0.3, no_contact + 0.3, regions)
    np.testing.assert_allclose(lifted["relative"][0], [0.1 / 0.5, 0.1 / 0.7, 0.0], atol=1e-12)


# --- Monte Carlo noise ------------------------------------------------------------------------------

def test_noise_floor_of_a_constant_variance():
    variance = np.full((20, 20, 3), 0.04)  # sigma 0.2
    area = np.ones((20, 20), bool)
    assert st.mae_floor(variance, area) == pytest.approx(math.sqrt(2 / math.pi) * 0.2)
    # a Gaussian low-pass of independent pixels divides a constant variance by
    # sum_j w_j^2 ~ 1 / (4 pi sigma^2) (its continuous limit); sigma 0 leaves it as it is
    low = st.low_passed_variance(variance, 2.0)
    assert low[10, 10, 0] == pytest.approx(0.04 / (4 * math.pi * 4.0), rel=0.02)
    assert st.low_passed_variance(variance, 0.0) is variance


# --- intervals of a mean -----------------------------------------------------------------------------

def test_t_interval_is_a_hand_computed_t_interval():
    ci = st.t_interval([1.0, 2.0, 3.0])  # mean 2, s = 1, N = 3
    assert ci["mean"] == 2.0
    assert ci["high"] - 2.0 == pytest.approx(T_975_2 / math.sqrt(3), rel=1e-6)
    assert 2.0 - ci["low"] == pytest.approx(ci["high"] - 2.0)
    assert st.t_interval([0.5]) == {"mean": 0.5, "low": 0.5, "high": 0.5}
    assert st.t_interval([1.0, 2.0, 3.0], 0.9)["high"] < ci["high"]


def test_bootstrap_interval_holds_the_mean_and_is_seeded():
    values = np.random.default_rng(3).normal(0.1, 0.02, 30)
    ci = st.bootstrap_interval(values)
    assert ci["low"] < ci["mean"] < ci["high"] and ci["mean"] == pytest.approx(values.mean())
    assert ci == st.bootstrap_interval(values)  # seeded
    assert ci != st.bootstrap_interval(values, seed=1)
    # the standard error of the mean: the 95 % interval spans about 2 x 1.96 of it
    sem = values.std(ddof=1) / math.sqrt(len(values))
    assert (ci["high"] - ci["low"]) / (2 * 1.96 * sem) == pytest.approx(1.0, abs=0.2)


def test_bootstrap_interval_of_degenerate_values():
    ci = st.bootstrap_interval([0.2, 0.2, 0.2])  # every resample's mean is the mean
    assert ci["low"] == ci["mean"] == ci["high"] == pytest.approx(0.2)
    assert st.bootstrap_interval([0.3]) == {"mean": 0.3, "low": 0.3, "high": 0.3}
    with_nan = st.bootstrap_interval([0.1, np.nan, 0.3, 0.2])  # an empty region's NaN is left out
    assert with_nan == st.bootstrap_interval([0.1, 0.3, 0.2])
    assert all(math.isnan(v) for v in st.bootstrap_interval([np.nan, np.nan]).values())


def test_percentile_interval_of_replicates():
    assert st.percentile_interval(np.arange(101.0)) == [5.0, 95.0]
    assert st.percentile_interval(np.arange(101.0), (2.5, 97.5)) == [2.5, 97.5]


def test_intervals_refuse_bad_input():
    with pytest.raises(ValueError, match="values must be one-dimensional"):
        st.bootstrap_interval(np.zeros((3, 2)))
    with pytest.raises(ValueError, match="confidence must be in"):
        st.bootstrap_interval([0.1, 0.2], confidence=95)
    with pytest.raises(ValueError, match="values must hold at least one value"):
        st.t_interval([])
    with pytest.raises(ValueError, match="values must be one-dimensional"):
        st.t_interval(np.zeros((2, 2)))
    with pytest.raises(ValueError, match="replicates must be one-dimensional"):
        st.percentile_interval(np.zeros((2, 2)))
