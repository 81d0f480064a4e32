"""scenes.captures: the frame's spread, the press regions and the halves a calibration
fits and judges, analytically (the contact strength: tests/test_image_stats.py)."""

from __future__ import annotations

import numpy as np
import pytest

from scenes import captures


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
    from scenes.spec_read import default_spec

    camera = Camera.from_spec(default_spec())
    assert default_film(camera) == [320, 240]
    assert default_film(camera.scaled(160, 120)) == [160, 120]
    assert default_film(camera.scaled(80, 60)) == [80, 60]
