"""tactile-sim compare: Table 1 of a capture, its intervals, its backgrounds and alignment."""

from __future__ import annotations

import argparse
import json
import shutil

import numpy as np
import pytest

#: One 8-bit step, a fraction of full scale.
LSB = 1 / 255


# --- the table: analytic ----------------------------------------------------------------------


def test_rows_are_means_with_seeded_bootstrap_intervals():
    from studies.compare import table

    values = {s: {"mae": np.array([0.1, 0.2, 0.3, 0.4]), "ssim": np.full(4, 0.9), "psnr": np.array([20., 22, 24, 26])}
              for s in table.SCOPES}
    ids = ["a", "b", "c", "d"]
    row = table.row("m", {"method": "fast"}, values, ids, resamples=500, seed=3)
    mae = row["masked"]["mae"]
    assert mae["mean"] == pytest.approx(0.25) and mae["low"] < 0.25 < mae["high"]
    assert 0.1 <= mae["low"] and mae["high"] <= 0.4  # a mean of resampled taps stays within them
    assert row["full"]["ssim"] == {"mean": 0.9, "low": 0.9, "high": 0.9}  # no spread, no width
    assert table.row("m", {"method": "fast"}, values, ids, resamples=500, seed=3) == row  # seeded
    assert table.row("m", {}, values, ids, resamples=500, seed=4)["masked"]["mae"] != mae
    sub = table.subset(row, ["b", "d"], resamples=500, seed=3)
    assert sub["taps"] == 2 and sub["masked"]["mae"]["mean"] == pytest.approx(0.3) and sub["method"] == "fast"
    assert "| m | 4 | 0.2500 [" in table.markdown([row], "t")
    with pytest.raises(ValueError, match=r"ids must be taps of row 'm', got \['z'\]"):
        table.subset(row, ["z"])
    with pytest.raises(ValueError, match=r"values\['full'\]\['mae'\] has 4 taps for 3 ids"):
        table.row("m", {}, values, ids[:3])


def test_spread_picks_evenly_and_keeps_order():
    from studies.compare.run import spread

    ids = [f"{i:06d}_x" for i in range(10)]
    assert spread(ids, 3) == [ids[0], ids[4], ids[9]]  # linspace 0, 4.5, 9 rounded half to even
    assert spread(ids, None) == ids and spread(ids, 20) == ids
    with pytest.raises(ValueError, match="the number of taps must be >= 1, got 0"):
        spread(ids, 0)


# --- the backgrounds: added afterwards equals rendered with -------------------------------------


def test_a_background_added_to_the_led_terms_equals_rendering_with_it(tiny_capture, tiny_replay, tiny_spec):
    """clip(S + k_a i_a B) in the circle, S the no-background render, is the fast path's
    render on B (module doc of studies.compare.run): to float rounding, every tap."""
    from phong_reference.background import make_background
    from phong_reference.plugin import make_renderer
    from scenes.camera import Camera, reference_depth
    from scenes.dataset import load_sample, read_samples
    from scenes.geometry import membrane_mesh
    from studies.compare.run import with_background

    camera = Camera.from_spec(tiny_spec)
    mesh = membrane_mesh(tiny_spec)
    ref = reference_depth(mesh, camera)[0]
    depths = [load_sample(tiny_replay, r)[1] for r in read_samples(tiny_replay)]
    for name in ("solid", str(tiny_capture / "background.png")):
        B = make_background(name, camera)
        with_bg = make_renderer(tiny_spec, mesh, camera, ref, {"field": "plane", "background": name})
        without = make_renderer(tiny_spec, mesh, camera, ref, {"field": "plane", "background": "none"})
        for depth in depths:
            composed = with_background(without.render(depth), B, tiny_spec.material.ambient, camera.mask)
            np.testing.assert_allclose(composed, with_bg.render(depth), atol=1e-6)


# --- compare, end to end ------------------------------------------------------------------------


def test_compare_finds_the_settings_the_capture_was_made_with(compare_result):
    """The capture is the fast path's (plane field, solid background): that row is the best,
    at the 8-bit files' rounding, and every other row is worse."""
    result, out = compare_result
    rows = {r["label"]: r for r in result["rows"]}
    own = rows["fast: plane, background solid"]
    assert result["best_fast"] == own["label"]
    assert own["masked"]["mae"]["high"] < LSB and own["masked"]["ssim"]["low"] > 0.99
    assert own["full"]["mae"]["mean"] < own["masked"]["mae"]["mean"]  # the black border agrees exactly
    # its contacts, where the real taps differ from the real no-contact image, as strong as the capture's
    assert own["contact"]["mae"]["high"] < 2 * LSB and own["strength"]["median"] == pytest.approx(1.0, abs=0.02)
    assert result["contact"].startswith("where each real tap differs") and len(result["real_strength"]) == 4
    # its strength splits into a level and a relative change each as the capture's, and its
    # no-contact image is as uneven as the capture's
    budget = own["contrast"]
    assert budget["level_ratio"] == pytest.approx([1.0] * 3, abs=0.02)
    assert budget["relative_ratio"] == pytest.approx([1.0] * 3, abs=0.05)
    assert budget["spread_ratio"] == pytest.approx([1.0] * 3, abs=0.05)
    assert budget["range"] == pytest.approx(budget["real_range"], rel=0.02)
    assert rows["fast: plane, background none"]["contrast"]["level_ratio"][0] < 0.9  # the capture has a background
    for label, r in rows.items():
        if label != own["label"]:
            assert r["masked"]["mae"]["mean"] > 10 * own["masked"]["mae"]["mean"], label
    assert set(rows) == {f"fast: {f}, background {b}" for f in ("plane", "linear") for b in ("none", "solid", "real")} \
        | {"reference: tests.fake_renderer"}
    assert rows["reference: tests.fake_renderer"]["taps"] == 2 and own["taps"] == 4
    assert [r["taps"] for r in result["on_reference_taps"]] == [2] * len(rows)
    assert not result["alignment"]["applied"] and result["mask"]["pixels"] > 0
    saved = json.loads((out / "table.json").read_text())
    assert saved["best_fast"] == own["label"] and saved["rows"][0]["ids"] == result["taps"]
    md = (out / "table.md").read_text()
    assert "| fast: plane, background solid | 4 | 0.000" in md and "On the reference's 2 taps only" in md
    for name in ("report.html", "metrics.png", "error_maps.png", "examples.png"):
        assert (out / name).stat().st_size > 500, name


def test_compare_judges_the_held_out_half_alone(tiny_capture, tmp_path):
    from studies.compare.run import compare, heldout_ids

    assert heldout_ids(["a", "b", "c", "d", "e"]) == ["b", "d"]
    result = compare(tiny_capture, tmp_path / "t", fields=("plane",), backgrounds=("solid",), reference=False,
                     heldout=True, bootstrap=50, progress=False)
    assert result["heldout"] and result["taps"] == ["000001_sphere", "000003_cylinder"]
    assert result["rows"][0]["strength"]["per_tap"] == pytest.approx([1.0, 1.0], abs=0.03)


def test_compare_applies_the_captures_alignment(tmp_path, tiny_spec, session_env):
    """A capture whose images were moved by a known alignment, and says so, matches the
    fast path moved by it; the same images without the block do not."""
    from scenes.geometry import membrane_mesh
    from scenes.profile import Alignment
    from studies.compare.run import compare
    from tests.fake_capture import capture_protocol, write_capture

    alignment = Alignment(rotation_rad=0.15, scale=1.05, shift_px=(2.0, -1.0))
    protocol = capture_protocol(tiny_spec, membrane_mesh(tiny_spec))
    root = write_capture(tmp_path / "capture", tiny_spec, protocol, background="none", alignment=alignment)
    kwargs = {"fields": ("plane",), "backgrounds": ("none",), "reference": False, "bootstrap": 100,
              "progress": False}
    aligned = compare(root, tmp_path / "aligned", **kwargs)
    assert aligned["alignment"]["applied"] and aligned["alignment"]["block"]["method"] == "registration"
    plain = shutil.copytree(root, tmp_path / "plain")
    meta = json.loads((plain / "dataset.json").read_text())
    del meta["alignment"]
    (plain / "dataset.json").write_text(json.dumps(meta))
    unaligned = compare(plain, tmp_path / "unaligned", **kwargs)
    assert not unaligned["alignment"]["applied"]
    near, far = (r["rows"][0]["masked"]["mae"]["mean"] for r in (aligned, unaligned))
    assert near < LSB and far > 5 * near, (near, far)


def test_a_peer_that_cannot_run_says_why(tiny_capture, tmp_path):
    """Taxim renders an imported set's ball presses: on a capture of the rig's indenters it
    is listed with its reason, and the table is made without it."""
    from studies.compare.run import compare

    result = compare(tiny_capture, tmp_path / "t", fields=("plane",), backgrounds=("solid",), reference=False,
                     peers=("taxim",), bootstrap=50, progress=False)
    status = result["peers"]["taxim"]
    assert not status["ran"] and ("imported set" in status["why"] or "pip install" in status["why"]), status
    assert all(r["method"] != "peer" for r in result["rows"])
    assert f"Peer taxim not scored: {status['why']}" in (tmp_path / "t" / "table.md").read_text()
    with pytest.raises(ValueError, match=r"peers must be some of \('taxim',\), got 'sapien'"):
        compare(tiny_capture, tmp_path / "u", fields=("plane",), backgrounds=("solid",), reference=False,
                peers=("sapien",), progress=False)


def test_compare_refuses_bad_input(tiny_capture, tmp_path):
    from studies.compare.run import compare

    with pytest.raises(ValueError, match=r"fields must be some of \('linear', 'plane', 'geodesic', 'transport'\)"):
        compare(tiny_capture, tmp_path, fields=("flat",))
    with pytest.raises(ValueError, match=r"backgrounds must be some of \('none', 'solid', 'real'\), got \['sky'\]"):
        compare(tiny_capture, tmp_path, backgrounds=("sky",), reference=False)
    with pytest.raises(ValueError, match="give backgrounds or a profile, not both"):
        compare(tiny_capture, tmp_path, profile="p.toml", backgrounds=("none",))
    with pytest.raises(ValueError, match="options must not hold 'field'"):
        compare(tiny_capture, tmp_path, options={"field": "plane"})
    bare = shutil.copytree(tiny_capture, tmp_path / "bare")
    (bare / "background.png").unlink()
    with pytest.raises(ValueError, match=r"background 'real' needs the capture's no-contact image"):
        compare(bare, tmp_path / "out", backgrounds=("real",), reference=False)
    assert not (tmp_path / "out").exists()  # refused before any render


def test_compare_command_through_its_registry(tiny_capture, tmp_path, capsys):
    """The plugin's register() on a registry of our own (its entry point needs a pip
    install): arguments reach compare, and the table is printed."""
    from scenes.cli import Registry
    from studies.compare.cli import register

    parser = argparse.ArgumentParser(prog="tactile-sim")
    commands = parser.add_subparsers(dest="command")
    register(Registry(commands, commands))  # compare adds no bench
    out = tmp_path / "table"
    args = parser.parse_args(["compare", str(tiny_capture), "--out", str(out), "--no-reference", "--fields", "plane",
                              "--backgrounds", "solid", "--taps", "2", "--bootstrap", "50", "--seed", "2",
                              "--workers", "1", "--quiet", "--elastic", "published"])
    assert args.func(args) == 0
    printed = capsys.readouterr().out
    assert "| fast: plane, background solid | 2 |" in printed and "table.json" in printed
    result = json.loads((out / "table.json").read_text())
    assert result["bootstrap"] == 50 and result["seed"] == 2 and result["options"] == {"elastic": "published"}
    assert result["reference_taps"] == [] and len(result["taps"]) == 2
    with pytest.raises(SystemExit):
        parser.parse_args(["compare", str(tiny_capture), "--out", str(out), "--taps", "0"])
    assert "must be a whole number >= 1, got 0" in capsys.readouterr().err
