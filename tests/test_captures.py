"""scenes.captures: the contact strength, the press regions and the halves a calibration
fits and judges, analytically."""

from __future__ import annotations

import numpy as np
import pytest

from scenes import captures


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
    out = captures.contact_strength(images, no_contact, regions)
    assert out[0] == pytest.approx(0.2) and out[1] == pytest.approx(0.05) and np.isnan(out[2])
    # one no-contact frame per image, and one region for all
    per_image = captures.contact_strength(images, np.repeat(no_contact[None], 3, axis=0), regions[0])
    assert per_image[0] == pytest.approx(0.2) and per_image[1] == 0.0
    # simulated over real: a simulation twice as strong has the ratio 2
    sim = no_contact + 2 * (images - no_contact)
    ratio = captures.contact_strength(sim, no_contact, regions) / out
    assert ratio[:2] == pytest.approx([2.0, 2.0])


@pytest.mark.parametrize("args, match", [
    ((np.zeros((2, 4, 4)), np.zeros((4, 4, 3)), np.ones((4, 4), bool)), r"images must be \(N, H, W, 3\)"),
    ((np.zeros((2, 4, 4, 3)), np.zeros((4, 5, 3)), np.ones((4, 4), bool)), r"no_contact must be \(H, W, 3\) or"),
    ((np.zeros((2, 4, 4, 3)), np.zeros((4, 4, 3)), np.ones((3, 4, 4), bool)), r"regions must be \(N, H, W\) or"),
])
def test_contact_strength_refuses_bad_shapes(args, match):
    with pytest.raises(ValueError, match=match):
        captures.contact_strength(*args)


def test_contact_contrast_splits_the_strength_into_level_and_relative_change():
    no_contact = np.full((6, 8, 3), [0.2, 0.4, 0.5])
    regions = np.zeros((2, 6, 8), bool)
    regions[0, 1:3, 2:6] = True  # region 1 stays empty
    images = np.repeat(no_contact[None], 2, axis=0)
    images[0][regions[0]] += [0.1, -0.1, 0.0]
    got = captures.contact_contrast(images, no_contact, regions)
    np.testing.assert_allclose(got["level"][0], [0.2, 0.4, 0.5])
    np.testing.assert_allclose(got["change"][0], [0.1, 0.1, 0.0], atol=1e-12)
    np.testing.assert_allclose(got["relative"][0], [0.5, 0.25, 0.0], atol=1e-12)
    assert np.isnan(got["level"][1]).all() and np.isnan(got["relative"][1]).all()
    # the strength is the channels' mean change, and a camera that doubles every value
    # doubles the level, not the relative change
    assert captures.contact_strength(images, no_contact, regions)[0] == pytest.approx(0.2 / 3)
    doubled = captures.contact_contrast(2 * images, 2 * no_contact, regions)
    np.testing.assert_allclose(doubled["relative"][0], got["relative"][0], atol=1e-12)
    # an offset (a pedestal) raises the level and dilutes the relative change
    lifted = captures.contact_contrast(images + 0.3, no_contact + 0.3, regions)
    np.testing.assert_allclose(lifted["relative"][0], [0.1 / 0.5, 0.1 / 0.7, 0.0], atol=1e-12)


def test_frame_spread_is_a_low_and_a_high_percentile_inside():
    image = np.ones((10, 10, 3))
    image[:, :5, 0] = 3.0  # half the red channel three times brighter
    image[0, 0] = 100.0  # outside: not counted
    inside = np.ones((10, 10), bool)
    inside[0, 0] = False
    got = captures.frame_spread(image, inside)
    assert got["range"][0] == pytest.approx(3.0) and got["spread"][0] == pytest.approx(2.0)
    assert got["range"][1] == got["range"][2] == 1.0 and got["spread"][1] == 0.0
    # a camera's gain and offset leave a change over the spread as it was
    change = 0.5
    moved = captures.frame_spread(2.0 * image + 0.3, inside)
    assert 2.0 * change / moved["spread"][0] == pytest.approx(change / got["spread"][0])
    assert np.isnan(captures.frame_spread(np.zeros((4, 4, 3)), np.ones((4, 4), bool))["range"]).all()
    with pytest.raises(ValueError, match=r"image must be \(H, W, 3\) and inside \(H, W\)"):
        captures.frame_spread(image, inside[:5])
    with pytest.raises(ValueError, match="inside selects no pixel"):
        captures.frame_spread(image, np.zeros((10, 10), bool))


def test_press_regions_take_an_annotated_disc_else_the_change():
    background = np.full((20, 30, 3), 0.5)
    images = np.repeat(background[None], 2, axis=0)
    images[1, 12:15, 20:24] += 0.2
    inside = np.ones((20, 30), bool)
    inside[:, :2] = False
    regions = captures.press_regions([{"contact_center_px": [3.0, 4.0], "contact_radius_px": 2.0}, {}], images,
                                     background, inside)
    disc = captures.contact_disc((20, 30), (3.0, 4.0), 2.0)
    assert disc.sum() == 13 and disc[4, 3] and disc[4, 5] and not disc[4, 6]  # the 13 pixel centres within 2 px
    np.testing.assert_array_equal(regions[0], disc & inside)
    np.testing.assert_array_equal(regions[1], captures.contact_region(images[1], background, inside))
    assert regions[1, 13, 21] and not regions[1, 5, 5]


def test_halves_fit_the_even_samples_and_judge_the_odd_ones():
    for count, limit in [(49, 10), (49, 49), (10, 3), (2, 10), (7, 100), (1, 5)]:
        pick = captures.halves(count, limit)
        assert len(pick) == min(count, limit) and len(set(pick)) == len(pick)
        fitted = captures.split(len(pick))
        assert np.all(pick[fitted] % 2 == 0) and np.all(pick[~fitted] % 2 == 1), (count, limit)
    np.testing.assert_array_equal(captures.halves(49, 10), [0, 1, 12, 13, 24, 25, 36, 35, 48, 47])
    assert len(captures.halves(5, 0)) == 0


def test_real_taps_regions_scale_their_discs_to_a_film():
    images = np.full((2, 40, 60, 3), 0.5)
    images[1, 28:36, 8:16] = 0.9
    taps = captures.RealTaps(images, np.zeros((2, 40, 60)), np.zeros((40, 60)), ["a", "b"],
                             np.array([[20.0, 10.0, 8.0], [np.nan] * 3]))
    half = images[:, ::2, ::2]
    regions = taps.regions(np.full((20, 30, 3), 0.5), np.ones((20, 30), bool), half)
    np.testing.assert_array_equal(regions[0], captures.contact_disc((20, 30), (9.75, 4.75), 4.0))
    assert regions[1, 14:18, 4:8].all() and regions[1].sum() < 80
    sub = taps.subset([1])
    assert sub.ids == ["b"] and np.isnan(sub.discs).all()
    with pytest.raises(ValueError, match=r"discs must be \(2, 3\) \(u, v, radius px\)"):
        captures.RealTaps(images, np.zeros((2, 40, 60)), np.zeros((40, 60)), ["a", "b"], np.zeros((2, 2)))


def test_the_public_presses_are_found_where_the_environment_says(tmp_path, monkeypatch):
    from scenes.reference_data import TAXIM_ARCHIVE, TAXIM_ENV, require_taxim_archive

    (tmp_path / TAXIM_ARCHIVE).write_bytes(b"")
    monkeypatch.setenv(TAXIM_ENV, str(tmp_path))
    assert require_taxim_archive() == tmp_path / TAXIM_ARCHIVE
    monkeypatch.setenv(TAXIM_ENV, str(tmp_path / "elsewhere"))
    with pytest.raises(FileNotFoundError, match=r"the public GelSight ball presses \(dataPack_small\.npz\) are not at "
                                                r".*elsewhere \(set \$REAL_GELSIGHT_TAXIM"):
        require_taxim_archive()


def test_the_references_default_film_fits_a_small_camera():
    from pbr_tactile.plugin import default_film
    from scenes.camera import Camera
    from scenes.spec import default_spec

    camera = Camera.from_spec(default_spec())
    assert default_film(camera) == [320, 240]
    assert default_film(camera.scaled(160, 120)) == [160, 120]
    assert default_film(camera.scaled(80, 60)) == [80, 60]
