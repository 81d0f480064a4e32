"""The dents' profile study (studies.dent_profile) against profiles written in closed form."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from scenes.image_stats import ring_profile
from scenes.imports import contact_edge_px
from studies.dent_profile import main, press_profile

H, W = 120, 160
CENTRE = (81.3, 58.6)


def _press(tail, r0=14.0, amplitude=0.2):
    """A no-contact frame of 0.4 and a press whose change rises as (r / r0)^2 to the rim
    r0 and falls beyond it as ``tail(r)`` (1 at r0), the same in every channel."""
    v, u = np.mgrid[:H, :W]
    r = np.hypot(u - CENTRE[0], v - CENTRE[1])
    change = np.where(r <= r0, (r / r0) ** 2, tail(np.maximum(r, r0)))
    no_contact = np.full((H, W, 3), 0.4)
    return no_contact + amplitude * change[..., None], no_contact


def test_a_ring_profile_is_the_mean_over_each_ring():
    values = np.hypot(*np.meshgrid(np.arange(W) - 80.0, np.arange(H) - 60.0))
    radius, mean, count = ring_profile(values, (80.0, 60.0), 2.0, reach_px=40.0)
    assert len(radius) == 20 and radius[0] == 1.0 and count.sum() == (values < 40).sum()
    assert np.allclose(mean[4:], radius[4:], atol=0.2)  # a ring's mean radius is about its middle's (on the pixel lattice)
    with pytest.raises(ValueError, match=r"\(H, W\)"):
        ring_profile(np.zeros((4, 4, 3)), (1, 1), 1.0)


@pytest.mark.parametrize("pixel_mm", [0.125])
def test_an_exponential_tail_is_measured_as_written(pixel_mm):
    decay_px = 6.0
    image, no_contact = _press(lambda r: np.exp(-(r - 14.0) / decay_px))
    rim_px = contact_edge_px(image, no_contact, CENTRE, 16.0)
    assert rim_px == pytest.approx(14.0, abs=0.5)
    out = press_profile(image, no_contact, CENTRE, pixel_mm, rim_px, contact_px=14.0)
    assert out["floor"] == pytest.approx(0.0, abs=1e-3) and out["peak"] == pytest.approx(0.2, rel=0.1)
    l_mm = decay_px * pixel_mm
    assert out["half_mm"] == pytest.approx(l_mm * math.log(2), rel=0.12)
    assert out["tenth_mm"] == pytest.approx(l_mm * math.log(10), rel=0.08)
    assert out["decay_mm"] == pytest.approx(l_mm, rel=0.08) and out["better"] == "exponential"
    assert out["contact_mm"] == pytest.approx(14.0 * pixel_mm)


def test_a_power_tail_is_told_from_an_exponential_one():
    image, no_contact = _press(lambda r: (14.0 / r) ** 3)
    rim_px = contact_edge_px(image, no_contact, CENTRE, 16.0)
    out = press_profile(image, no_contact, CENTRE, 0.125, rim_px)
    assert out["better"] == "power" and out["power"] == pytest.approx(3.0, rel=0.1)
    # a half and a tenth of a cube's fall: 2^(1/3) and 10^(1/3) of the rim (the half less
    # closely: the rim's kink is averaged over its ring, which lowers the peak by 8 %)
    assert out["half_mm"] == pytest.approx(14.0 * 0.125 * (2 ** (1 / 3) - 1), rel=0.2)
    assert out["tenth_mm"] == pytest.approx(14.0 * 0.125 * (10 ** (1 / 3) - 1), rel=0.1)


def test_a_floor_of_drift_is_taken_off_before_the_widths():
    image, no_contact = _press(lambda r: np.exp(-(r - 14.0) / 6.0))
    drifted = image + 0.03  # the whole frame shifted: a drift the floor holds
    out = press_profile(drifted, no_contact, CENTRE, 0.125, 14.0)
    assert out["floor"] == pytest.approx(0.03, abs=0.003)
    assert out["decay_mm"] == pytest.approx(0.75, rel=0.12)


def test_bad_inputs_are_refused_by_name(tmp_path):
    image, no_contact = _press(lambda r: np.exp(-(r - 14.0) / 6.0))
    with pytest.raises(ValueError, match="no-contact frame"):
        press_profile(image[..., :2], no_contact, CENTRE, 0.125, 14.0)
    with pytest.raises(ValueError, match="must be > 0"):
        press_profile(image, no_contact, CENTRE, 0.0, 14.0)
    with pytest.raises(SystemExit):
        main([str(tmp_path), "--out", str(tmp_path / "o"), "--sim", "nameless"])


def test_a_capture_and_a_set_of_its_presses_are_measured_alike(tmp_path, mujoco_gl):
    """End to end on a synthetic Taxim pack (rings peaking 13.5 px out): the capture
    measured beside itself as a rendered set gives the same figures; a set with none of
    its presses is refused, naming both."""
    from scenes import imports, press_sets
    from scenes.spec_read import load_spec
    from studies.dent_profile import measure
    from test_import_capture import GELSIGHT, run_import, write_pack

    pack = write_pack(tmp_path / "dataPack.npz")
    run_import(tmp_path, pack, out="cap")
    out = measure(tmp_path / "cap", {"same": tmp_path / "cap"})
    real, same = out["sets"]["real"], out["sets"]["same"]
    assert out["presses"] == 3 and real["summary"]["measured"] == 3
    assert json.dumps(real) == json.dumps(same)  # (NaN rings near the centre compare as text)
    assert real["summary"]["rim_mm"]["median"] == pytest.approx(13.5 * 0.1245, rel=0.05)
    defaults = press_sets.DEFAULTS["taxim"]
    imports.import_capture(press_sets.read_taxim(pack), tmp_path / "other", load_spec(GELSIGHT), 5e-3,
                           defaults["pixel_m"])  # another ball: other sample ids
    with pytest.raises(ValueError, match="no sample ids in common"):
        measure(tmp_path / "cap", {"other": tmp_path / "other"})
