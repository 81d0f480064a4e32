"""The design loop (studies.design): sweeps, LED seating, scores, and a small run."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from scenes.reference_data import CAMERA_NOISE_RGB
from scenes.spec_read import load_spec
from studies.design import score, sweep

SENSORS = Path(__file__).parents[1] / "scenes" / "sensors"


@pytest.fixture(scope="module")
def thumb():
    return load_spec(SENSORS / "thumb.toml")


def test_sweeps_parse_and_bad_ones_are_refused_by_name(thumb):
    assert sweep.parse_sweep("pad_flatness=0.1,0.4") == ("pad_flatness", (0.1, 0.4))
    name, values = sweep.parse_sweep("thickness = 0.002:0.003:3")
    assert name == "thickness" and np.allclose(values, [0.002, 0.0025, 0.003])
    for text in ("pad_flatness", "=0.1", "pad_flatness=", "x=1:2", "x=1:2:0.5", "x=a,b"):
        with pytest.raises(ValueError, match="expected NAME=V1"):
            sweep.parse_sweep(text)
    assert set(sweep.parameters(thumb)) == {"width", "depth", "length", "tip_height", "pad_flatness", "tip_lean",
                                            "thickness", "led_height"}
    with pytest.raises(ValueError, match="'radius' is not one of sensor 'thumb'"):
        sweep.check_sweep(thumb, {"radius": [0.01]})
    with pytest.raises(ValueError, match="1 to 2 parameters"):
        sweep.check_sweep(thumb, {"width": [0.023], "depth": [0.017], "length": [0.05]})
    with pytest.raises(ValueError, match="distinct values"):
        sweep.check_sweep(thumb, {"width": [0.023, 0.023]})
    with pytest.raises(ValueError, match="not a finite number"):
        sweep.check_sweep(thumb, {"width": [np.nan]})
    with pytest.raises(ValueError, match="groups inside the tube"):
        sweep.check_sweep(load_spec(SENSORS / "geltip_2023.toml"), {"thickness": [0.002]})
    read_whole = dataclasses.replace(thumb, membrane=dataclasses.replace(thumb.membrane, shape="mesh"))
    with pytest.raises(ValueError, match="is a mesh file: only a shape family"):  # its family has no PARAMETERS
        sweep.check_sweep(read_whole, {"thickness": [0.002]})


def test_designs_seat_their_leds_on_their_own_membrane_and_impossible_ones_are_refused(thumb):
    from scenes.geometry import membrane_mesh

    # The shipped thumb's LEDs were seated by the same rule: seating them again moves nothing.
    seated = sweep.seat_leds(thumb.to_dict()["leds"], membrane_mesh(thumb), "thumb")
    assert np.allclose([led["position"] for led in seated], [led.position for led in thumb.leds], atol=2e-6)
    wide = sweep.design(thumb, {"width": 0.028})
    assert wide.refused is None and dict(wide.spec.membrane.params)["width"] == 0.028
    assert wide.spec.leds[0].position[0] > thumb.leds[0].position[0] + 0.002  # moved out with the membrane
    up = sweep.design(thumb, {"led_height": 0.01})
    assert up.refused is None and all(led.position[2] == pytest.approx(0.01) for led in up.spec.leds)
    out = sweep.design(thumb, {"pad_flatness": 0.95})  # beyond the family's bounds
    assert out.spec is None and "pad_flatness" in out.refused and "0.8" in out.refused
    lost = sweep.design(thumb, {"led_height": 0.2})  # above the tip
    assert lost.spec is None and "meet no membrane" in lost.refused
    grid = sweep.designs(thumb, {"pad_flatness": [0.95, 0.2], "thickness": [0.002, 0.003]})
    assert [d.values for d in grid] == [(("pad_flatness", a), ("thickness", b)) for a in (0.95, 0.2)
                                        for b in (0.002, 0.003)]
    assert [d.refused is None for d in grid] == [False, False, True, True]
    assert grid[3].spec.membrane.thickness == 0.003


def test_the_standard_tap_count_is_what_the_protocol_gives(thumb):
    from scenes.geometry import membrane_mesh
    from studies.design import loop

    taps = loop.standard_taps(thumb, membrane_mesh(thumb))
    assert loop.standard_tap_count() == len(taps) == 80
    assert loop.standard_tap_count(7) == len(loop.spread(len(taps), 7)) == 7
    assert loop.standard_tap_count(500) == 80
    for bad in (0, -3, 2.5, True):
        with pytest.raises(ValueError, match="count must be a whole number >= 1"):
            loop.standard_tap_count(bad)


def test_contrast_is_a_percentile_of_the_change_in_noise_units():
    no_contact = np.full((20, 30, 3), 0.2)
    frame = no_contact.copy()
    assert score.tap_contrast(no_contact, frame) == 0.0  # nothing changes
    frame[5:15, 5:15, 2] += 0.06  # blue: 10 noise units
    frame[5:15, 5:15, 0] += 0.06  # red: 5 noise units
    assert score.tap_contrast(no_contact, frame) == pytest.approx(0.06 / CAMERA_NOISE_RGB[2])
    assert score.changed_pixels(no_contact, frame).sum() == 100
    frame[10, 10, 1] += 1.0  # one hot pixel does not set the 95th percentile
    assert score.tap_contrast(no_contact, frame) == pytest.approx(10.0)
    with pytest.raises(ValueError, match="noise must be 3 positive"):
        score.tap_contrast(no_contact, frame, noise=(0.01, 0.0, 0.01))
    with pytest.raises(ValueError, match="must both be"):
        score.tap_contrast(no_contact, frame[:, :5])


def test_the_score_falls_with_dead_taps_and_uneven_contrast():
    depth = np.full(20, 0.002)
    even = score.design_score(np.full(20, 40.0), depth)
    assert even["score"] == pytest.approx(20000.0) and even["evenness"] == 1.0 and even["dead_share"] == 0.0
    holes = np.full(20, 40.0)
    holes[:4] = 1.0  # a fifth of the membrane under the noise
    dead = score.design_score(holes, depth)
    assert dead["dead_share"] == 0.2 and dead["score"] < even["score"] / 10
    assert dead["median"] == even["median"]
    with pytest.raises(ValueError, match="equal"):
        score.design_score(np.ones(3), np.ones(4))
    with pytest.raises(ValueError, match="depth_m must be finite and > 0"):
        score.design_score(np.ones(3), np.zeros(3))
    with pytest.raises(ValueError, match="contrast must be finite"):
        score.design_score(np.array([1.0, -1.0]), np.ones(2))


@pytest.mark.slow
def test_a_small_sweep_writes_a_ranked_report(thumb, tmp_path):
    from studies.design.loop import run

    data = run(thumb, {"pad_flatness": [0.1, 0.7], "led_height": [0.0]}, tmp_path, taps=4, reference=False,
               progress=False)
    assert [d["refused"] for d in data["designs"]] == [None, None]
    assert data["taps_per_design"] == 4 and all(len(d["taps"]) == 4 for d in data["designs"])
    s = [d["score"]["score"] for d in data["designs"]]
    assert s[data["best"]] == max(s) and s[data["worst"]] == min(s)
    assert all(d["score"]["dead_share"] < 1 for d in data["designs"])
    assert json.loads((tmp_path / "design.json").read_text())["ranking"] == data["ranking"]
    for name in ("summary.md", "sweep.png", "maps.png", "check.png"):
        assert (tmp_path / name).stat().st_size > 0
    assert "pad_flatness = 0.1" in (tmp_path / "summary.md").read_text()


@pytest.mark.slow
def test_the_reference_checks_the_best_and_the_worst_on_the_same_taps(thumb, tmp_path):
    pytest.importorskip("mitsuba", reason="Mitsuba 3 is not installed (pip install '.[pbr]')")
    from studies.design.loop import run
    from studies.pbr_field_comparison.frames import QUICK

    data = run(thumb, {"thickness": [0.0015, 0.004]}, tmp_path, taps=3, reference_taps=2, settings=QUICK,
               progress=False)
    check = data["reference_check"]
    assert [r["tap"] for r in check["taps"]] == [0, 2]
    for r in check["taps"]:
        assert r["fast_best"] >= 0 and r["reference_best"] > 0 and r["reference_worst"] > 0
        assert r["fast_ratio"] == pytest.approx(r["fast_best"] / r["fast_worst"])
        assert r["agrees"] == ((r["fast_ratio"] > 1) == (r["reference_ratio"] > 1))
    assert data["reference_settings"]["width"] == QUICK.width
    assert len(list((tmp_path / "reference_cache").glob("*.npy"))) == 2 * (1 + 2)  # no-contact frames shared
    for d in data["designs"]:
        reach = d["reference_reach"]
        assert 0 <= reach["dark_share"] < 1 and 0 <= reach["evenness"] <= 1 and reach["p99_5"] > 0
    assert "The reference agrees with the fast path's ranking on" in (tmp_path / "summary.md").read_text()
