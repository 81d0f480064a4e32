"""tactile-sim import: a published capture as a capture dataset. The rim's estimator and
the ball's depth analytically first, then a synthetic archive end to end with every bad
input, then the public GelSight set when it is beside the repository."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from scenes import imports, press_sets

GELSIGHT = Path(__file__).resolve().parents[1] / "scenes" / "sensors" / "gelsight.toml"
TAXIM_SET = Path(__file__).resolve().parents[2] / "shared" / "data" / "real_gelsight_taxim"


def ring_press(shape, centre, rim_px, width_px=3.0, peak=0.2):
    """A frame whose change from a grey no-contact frame is a ring of radius ``rim_px``:
    (no_contact, frame)."""
    v, u = np.mgrid[: shape[0], : shape[1]]
    r = np.hypot(u - centre[0], v - centre[1])
    no_contact = np.full((*shape, 3), 0.4)
    return no_contact, no_contact + peak * np.exp(-0.5 * ((r - rim_px) / width_px) ** 2)[..., None]


# --- analytic ----------------------------------------------------------------------------------


@pytest.mark.parametrize("rim", [9.3, 12.0, 14.7])
def test_the_rim_is_where_the_change_peaks_round_the_centre(rim):
    no_contact, frame = ring_press((120, 160), (80.0, 61.0), rim)
    assert imports.contact_edge_px(frame, no_contact, (80.0, 61.0), 16.06) == pytest.approx(rim, abs=0.15)


def test_a_rim_at_the_end_of_the_search_is_refused():
    no_contact, frame = ring_press((120, 160), (80.0, 61.0), 30.0)
    with pytest.raises(ValueError, match=r"changes the image most at .* at the end of the search .*no rim found"):
        imports.contact_edge_px(frame, no_contact, (80.0, 61.0), 16.06)


def test_ball_depth_from_its_contact_circle():
    R = 2e-3
    for d in (0.2e-3, 1e-3, 1.9e-3):
        a = math.sqrt(2 * R * d - d * d)
        assert imports.ball_depth(a, R) == pytest.approx(d, rel=1e-9)
    with pytest.raises(ValueError, match=r"a contact circle 2\.12 mm in radius is larger than a ball 2 mm in radius "
                                         r"allows"):
        imports.ball_depth(2.12e-3, R)


# --- a synthetic archive, end to end -----------------------------------------------------------


def write_pack(path: Path, frames=None, f0=None, centres=None, radii=None, **extra) -> Path:
    """A Taxim data pack (BGR uint8) of three ring presses, with any array replaced."""
    shape = (120, 160)
    centres = np.array([[60.0, 50.0], [90.0, 70.0], [110.0, 40.0]]) if centres is None else centres
    if frames is None or f0 is None:
        made = [ring_press(shape, c, 13.5) for c in centres]
        f0 = (made[0][0] * 255).round().astype(np.uint8) if f0 is None else f0
        frames = np.stack([(m[1] * 255).round().astype(np.uint8) for m in made]) if frames is None else frames
    radii = np.full(len(centres), 17) if radii is None else radii
    arrays = {"f0": f0, "imgs": frames, "touch_center": centres, "touch_radius": radii,
              "names": np.array([f"frame_{i}.jpg" for i in range(len(centres))]), **extra}
    np.savez(path, **{k: v for k, v in arrays.items() if v is not None})
    return path


def run_import(tmp_path, pack, out="capture", **kwargs):
    from scenes.spec_read import load_spec

    defaults = press_sets.DEFAULTS["taxim"]
    return imports.import_capture(press_sets.read_taxim(pack), tmp_path / out, load_spec(GELSIGHT), defaults["ball_m"],
                                  defaults["pixel_m"], **kwargs)


def test_an_archive_becomes_a_capture_that_replays(tmp_path, mujoco_gl):
    from scenes.dataset import read_samples
    from scenes.images import read_rgb
    from scenes.replay import read_capture

    pack = write_pack(tmp_path / "dataPack_small.npz")
    summary = run_import(tmp_path, pack)
    root = tmp_path / "capture"
    capture = read_capture(root)  # what replay, compare and diagnose read
    assert capture.spec.camera.width == 160 and capture.objects == ("ball_4mm",)
    meta = json.loads((root / "dataset.json").read_text())
    assert meta["source"] == "real" and meta["import"]["depth"] == "profile" and meta["image_size"] == [160, 120]
    records = read_samples(root)
    assert [r["source_name"] for r in records] == ["frame_0.jpg", "frame_1.jpg", "frame_2.jpg"]
    # a rim of 13.5 px at 0.1245 mm on a 2 mm ball: d = R - sqrt(R^2 - a^2)
    a = 13.5 * 0.1245e-3
    expected = 2e-3 - math.sqrt(4e-6 - a * a)
    for r in records:
        assert r["measured_depth"] == pytest.approx(expected, abs=0.02e-3)
        assert r["contact_edge_px"] == pytest.approx(13.5, abs=0.15) and r["contact_radius_px"] == 17
    assert summary["presses"] == 3
    # channels: stored BGR, read back RGB
    f0 = np.load(pack)["f0"]
    np.testing.assert_allclose(read_rgb(root / "background.png"), f0[..., ::-1] / 255.0, atol=1e-7)
    # each contact point is where the camera sees the annotated centre
    from scenes.camera import Camera, project

    camera = Camera.from_spec(capture.spec)
    for r, centre in zip(records, np.load(pack)["touch_center"]):
        np.testing.assert_allclose(project(np.array(r["contact_point"]), camera), centre, atol=1e-6)
    # again: nothing to do, nothing changed
    before = {p.name: p.stat().st_mtime_ns for p in (root / "images").iterdir()}
    run_import(tmp_path, pack)
    assert {p.name: p.stat().st_mtime_ns for p in (root / "images").iterdir()} == before
    # the replay renders each press where the archive shows it
    from phong_reference import plugin as phong
    from scenes.replay import replay

    replay(capture, tmp_path / "sim", phong, {"field": "plane", "background": "none"}, workers=1, progress=False)
    sim = read_rgb(tmp_path / "sim" / "images" / f"{records[1]['id']}.png")
    change = sim.sum(axis=2)
    v, u = np.unravel_index(np.argmax(change), change.shape)
    assert math.hypot(u - 90, v - 70) < 14  # within the rim of the press at (90, 70)


def test_an_import_into_another_capture_is_refused_and_overwrites_nothing(tmp_path):
    pack = write_pack(tmp_path / "dataPack_a.npz")
    run_import(tmp_path, pack)
    root = tmp_path / "capture"
    files = {p: p.read_bytes() for p in root.rglob("*") if p.is_file()}
    other = write_pack(tmp_path / "dataPack_b.npz", centres=np.array([[50.0, 50.0], [100.0, 60.0], [70.0, 80.0]]))
    with pytest.raises(Exception, match=r"already holds a dataset with different"):
        run_import(tmp_path, other)
    assert {p: p.read_bytes() for p in root.rglob("*") if p.is_file()} == files
    (tmp_path / "busy").mkdir()
    (tmp_path / "busy" / "notes.txt").write_text("mine")
    with pytest.raises(Exception, match=r"holds files but no dataset; import into an empty or new folder"):
        run_import(tmp_path, pack, out="busy")
    assert sorted(p.name for p in (tmp_path / "busy").iterdir()) == ["notes.txt"]


def test_bad_archives_are_refused_by_name(tmp_path):
    f0 = np.zeros((120, 160, 3), np.uint8)
    cases = [
        (dict(f0=np.zeros((60, 80, 3), np.uint8)), r"frames of unequal size: the presses are 160x120 px, the "
                                                   r"no-contact frame f0 80x60 px"),
        (dict(centres=np.array([[60.0, 50.0], [170.0, 70.0], [110.0, 40.0]])),
         r"press 1 \(frame_1\.jpg\): its centre \(170, 70\) px lies outside the 160x120 frame"),
        (dict(radii=np.array([17, 0, 17])), r"press 1 \(frame_1\.jpg\): its radius must be a positive number"),
        (dict(frames=np.zeros((3, 120, 160, 3), np.float32), f0=f0), r"imgs must be \(N, H, W, 3\) uint8"),
    ]
    for i, (kwargs, match) in enumerate(cases):
        pack = write_pack(tmp_path / f"dataPack_{i}.npz", **kwargs)
        with pytest.raises(ValueError, match=match):
            run_import(tmp_path, pack, out=f"out{i}")
        assert not (tmp_path / f"out{i}").exists()
    no_f0 = tmp_path / "nof0" / "dataPack.npz"
    no_f0.parent.mkdir()
    np.savez(no_f0, imgs=np.zeros((1, 4, 4, 3), np.uint8), touch_center=np.zeros((1, 2)), touch_radius=np.ones(1))
    with pytest.raises(ValueError, match=r"has no no-contact frame \(key 'f0'\); a capture needs one"):
        press_sets.read_taxim(no_f0.parent)  # a folder holding one pack
    ragged = tmp_path / "ragged.npz"
    frames = np.empty(2, object)
    frames[0], frames[1] = np.zeros((120, 160, 3), np.uint8), np.zeros((60, 80, 3), np.uint8)
    np.savez(ragged, f0=f0, imgs=frames, touch_center=np.zeros((2, 2)), touch_radius=np.ones(2))
    with pytest.raises(ValueError, match=r"imgs is not one regular array .*frames of unequal size or Python objects"):
        press_sets.read_taxim(ragged)
    (tmp_path / "two").mkdir()
    for name in ("dataPack_1.npz", "dataPack_2.npz"):
        write_pack(tmp_path / "two" / name)
    with pytest.raises(ValueError, match=r"a folder must hold exactly one dataPack\*\.npz, found \['dataPack_1\.npz', "
                                         r"'dataPack_2\.npz'\]"):
        press_sets.read_taxim(tmp_path / "two")
    with pytest.raises(ValueError, match=r"its annotated radius, 17\.00 px at 0\.1245 mm a pixel: a contact circle "
                                         r"2\.12 mm in radius is larger than a ball 2 mm in radius allows"):
        run_import(tmp_path, write_pack(tmp_path / "dataPack_r.npz"), out="radius", depth="radius")


def test_a_rim_share_puts_the_contact_rim_outside_the_peak_and_caps_it_at_the_ball(tmp_path):
    from scenes.dataset import read_meta, read_samples

    pack = write_pack(tmp_path / "dataPack.npz")  # rings peaking 13.5 px from their centres
    R = press_sets.DEFAULTS["taxim"]["ball_m"] / 2
    pixel = press_sets.DEFAULTS["taxim"]["pixel_m"]
    run_import(tmp_path, pack, out="plain")
    plain = {r["id"]: r for r in read_samples(tmp_path / "plain")}
    share = 0.9
    summary = run_import(tmp_path, pack, out="inside", rim_share=share)
    assert summary["rim_share"] == share and summary["rims_capped"] == 0
    for r in read_samples(tmp_path / "inside"):
        edge = plain[r["id"]]["contact_edge_px"]
        assert r["contact_edge_px"] == pytest.approx(edge)  # the peak, as found
        assert r["measured_depth"] == pytest.approx(imports.ball_depth(edge / share * pixel, R), rel=1e-9)
        assert r["measured_depth"] > plain[r["id"]]["measured_depth"] and r["contact_radius_capped"] is False
    assert read_meta(tmp_path / "inside")["import"]["rim_share"] == share
    summary = run_import(tmp_path, pack, out="capped", rim_share=0.8)  # 13.5 / 0.8 px is past the 16.1 px ball
    assert summary["rims_capped"] == 3
    for r in read_samples(tmp_path / "capped"):
        assert r["contact_radius_capped"] is True
        assert r["measured_depth"] == pytest.approx(imports.ball_depth(imports.RIM_CAP * R, R), rel=1e-9)
    for value, match in ((0.0, r"rim_share must be in \(0, 1\]"), (1.2, r"rim_share must be in \(0, 1\]")):
        with pytest.raises(ValueError, match=match):
            run_import(tmp_path, pack, out="bad", rim_share=value)
    with pytest.raises(ValueError, match=r"rim_share applies to the rim fitted to the image"):
        run_import(tmp_path, pack, out="bad", depth="radius", rim_share=0.9)
    assert not (tmp_path / "bad").exists()


def test_the_import_command_prints_and_refuses(tmp_path, capsys):
    from scenes.cli import main

    pack = write_pack(tmp_path / "dataPack_small.npz")
    assert main(["import", "taxim", str(pack), "--out", str(tmp_path / "cap"), "--spec", str(GELSIGHT)]) == 0
    out = capsys.readouterr().out
    assert "3 presses of" in out and "ball_4mm, depth by profile: median 0.9" in out
    assert main(["import", "taxim", str(tmp_path / "missing.npz"), "--out", str(tmp_path / "x")]) == 1
    err = capsys.readouterr().err
    assert "tactile-sim import: error: archive" in err and "missing.npz does not exist" in err


# --- the public set --------------------------------------------------------------------------


@pytest.fixture(scope="module")
def taxim_set():
    pack = TAXIM_SET / "dataPack_small.npz"
    if not pack.is_file():
        pytest.skip(f"the public GelSight ball presses are not at {TAXIM_SET} (../shared/data/real_gelsight_taxim)")
    return pack


def test_the_public_set_imports_at_about_a_millimetre(tmp_path, taxim_set):
    from scenes.dataset import read_samples

    summary = run_import(tmp_path, taxim_set)
    assert summary["presses"] == 49
    depths = np.array([r["measured_depth"] for r in read_samples(tmp_path / "capture")])
    # Taxim's own simulation presses 1.0 mm; the rims fitted here put the presses at 0.6-1.4 mm
    assert 0.8e-3 < np.median(depths) < 1.3e-3 and depths.min() > 0.4e-3 and depths.max() < 1.6e-3
