"""tactile-sim import folder: a folder of press images, a no-contact frame and a table. A
quarter turn analytically first, then small sets made here (landscape and portrait, CSV
and JSON), the two formats against each other, and every bad input by the command."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from scenes import imports, press_sets

GELSIGHT = Path(__file__).resolve().parents[1] / "scenes" / "sensors" / "gelsight.toml"
CENTRES = ((60.0, 50.0), (90.0, 70.0), (110.0, 40.0))
RIM_PX = 13.5


def ring(shape, centre, rim_px=RIM_PX, width_px=3.0, peak=0.2, tint=(0.0, 0.0, 0.0)):
    """A grey no-contact frame, tinted per channel, and a press on it whose change is a ring
    of radius ``rim_px`` about ``centre`` (u, v): uint8 (no_contact, frame)."""
    v, u = np.mgrid[: shape[0], : shape[1]]
    r = np.hypot(u - centre[0], v - centre[1])
    f0 = np.full((*shape, 3), 0.4) + np.asarray(tint)
    frame = f0 + peak * np.exp(-0.5 * ((r - rim_px) / width_px) ** 2)[..., None]
    return (f0 * 255).round().astype(np.uint8), (frame * 255).round().astype(np.uint8)


def make_folder(folder: Path, shape=(120, 160), centres=CENTRES, table="presses.csv", no_contact="background.png",
                columns=("image", "x", "y", "radius"), extra=None, bgr=False, records=None) -> Path:
    """A folder of ring presses (RGB PNGs, the no-contact frame's red raised so that a swap
    of channels shows), its table with ``columns`` (and ``extra`` {column: values})."""
    folder.mkdir(parents=True, exist_ok=True)
    order = (lambda a: a[..., ::-1]) if bgr else (lambda a: a)
    rows = []
    for i, c in enumerate(centres):
        f0, frame = ring(shape, c, tint=(0.2, 0.0, 0.0))
        Image.fromarray(order(frame)).save(folder / f"press_{i}.png")
        rows.append({"image": f"press_{i}.png", "x": c[0], "y": c[1], "radius": 17,
                     **{k: v[i] for k, v in (extra or {}).items()}})
    if no_contact:
        Image.fromarray(order(f0)).save(folder / no_contact)
    keys = [k for k in columns] + list(extra or {})
    if table.endswith(".json"):
        (folder / table).write_text(json.dumps([{k: r[k] for k in keys} for r in rows]))
    else:
        with open(folder / table, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=keys, extrasaction="ignore")
            w.writeheader()
            w.writerows(rows)
    if records is not None:
        (folder / "set.toml").write_text(records)
    return folder


def run(*argv):
    from scenes.cli import main

    return main(["import", *map(str, argv)])


# --- a quarter turn, analytically --------------------------------------------------------------


@pytest.mark.parametrize("degrees", [90, 180, 270])
def test_turning_the_frames_moves_the_annotations_with_them(degrees):
    h, w = 30, 50
    frames = np.zeros((2, h, w, 3))
    centres = np.array([[7.0, 4.0], [41.0, 22.0]])
    for k, (u, v) in enumerate(centres.astype(int)):
        frames[k, v, u] = 1.0
    archive = press_sets.Archive(no_contact=np.zeros((h, w, 3)), frames=frames, centres_px=centres,
                              radii_px=np.array([3.0, 3.0]), names=("a", "b"), path="made here")
    turned = press_sets.turn_archive(archive, degrees)
    assert turned.frames.shape[1:3] == ((w, h) if degrees != 180 else (h, w))
    for k in range(2):
        v, u = np.unravel_index(np.argmax(turned.frames[k, ..., 0]), turned.frames.shape[1:3])
        assert (u, v) == tuple(turned.centres_px[k])  # the annotated pixel is still the marked one
    back = press_sets.turn_archive(turned, 360 - degrees)
    np.testing.assert_array_equal(back.frames, archive.frames)
    np.testing.assert_array_equal(back.centres_px, archive.centres_px)
    with pytest.raises(ValueError, match=r"a turn must be one of \(0, 90, 180, 270\) degrees clockwise, got 45"):
        press_sets.turn_archive(archive, 45)


# --- small sets, end to end --------------------------------------------------------------------


def test_a_landscape_folder_imports_as_its_presses_show(tmp_path, capsys):
    from scenes.dataset import read_samples
    from scenes.images import read_rgb
    from scenes.replay import read_capture

    folder = make_folder(tmp_path / "set")
    assert run("folder", folder, "--out", tmp_path / "cap", "--spec", GELSIGHT, "--ball-mm", 4,
               "--pixel-mm", 0.1245) == 0
    out = capsys.readouterr().out
    assert "3 presses of" in out and "(folder, sensor gelsight" in out and "depth by profile" in out
    capture = read_capture(tmp_path / "cap")
    assert (capture.spec.camera.width, capture.spec.camera.height) == (160, 120)
    records = read_samples(tmp_path / "cap")
    a = RIM_PX * 0.1245e-3
    for r, c in zip(records, CENTRES):
        assert r["contact_center_px"] == list(c) and r["contact_edge_px"] == pytest.approx(RIM_PX, abs=0.15)
        assert r["measured_depth"] == pytest.approx(2e-3 - math.sqrt(4e-6 - a * a), abs=0.02e-3)
    # RGB as stored: the raised red stays red
    assert read_rgb(tmp_path / "cap" / "background.png")[0, 0, 0] == pytest.approx(0.6, abs=0.003)
    meta = json.loads((tmp_path / "cap" / "dataset.json").read_text())
    assert meta["import"]["format"] == "folder" and meta["import"]["turned_deg"] == 0
    assert meta["renderer"]["camera"]["channels"] == "stored RGB"


def test_a_portrait_folder_sets_the_camera_from_its_frames_or_is_turned(tmp_path, capsys):
    from scenes.dataset import read_samples
    from scenes.replay import read_capture

    portrait = [(c[1], c[0]) for c in CENTRES]  # (u, v) in a 120 x 160 frame
    folder = make_folder(tmp_path / "set", shape=(160, 120), centres=portrait)
    # the default: the camera's sensor is set from the frames, the frames kept as they are
    assert run("folder", folder, "--out", tmp_path / "kept", "--spec", GELSIGHT, "--ball-mm", 4) == 0
    kept = read_capture(tmp_path / "kept")
    assert (kept.spec.camera.width, kept.spec.camera.height) == (120, 160)
    meta = json.loads((tmp_path / "kept" / "dataset.json").read_text())
    assert meta["import"]["turned_deg"] == 0 and "the camera's sensor set from the 120x160 frames" in \
        meta["import"]["camera"]
    # the default pixel follows the spec: its camera's, a pixel of its at 160x120 (0.1245 mm), for as many pixels
    assert meta["import"]["pixel_mm"] == pytest.approx(0.1245, rel=2e-3)
    for r, c in zip(read_samples(tmp_path / "kept"), portrait):
        assert r["contact_center_px"] == list(c) and r["contact_edge_px"] == pytest.approx(RIM_PX, abs=0.15)
    # turned to the spec's landscape camera, the annotations with them
    assert run("folder", folder, "--out", tmp_path / "turned", "--spec", GELSIGHT, "--ball-mm", 4,
               "--turn", "auto") == 0
    assert "frames turned 90 deg clockwise" in capsys.readouterr().out
    turned = read_capture(tmp_path / "turned")
    assert (turned.spec.camera.width, turned.spec.camera.height) == (160, 120)
    assert json.loads((tmp_path / "turned" / "dataset.json").read_text())["import"]["turned_deg"] == 90
    for r, (u, v) in zip(read_samples(tmp_path / "turned"), portrait):
        assert r["contact_center_px"] == [160 - 1 - v, u]
        # the rim is found round the turned centre: the annotation moved with its frame
        assert r["contact_edge_px"] == pytest.approx(RIM_PX, abs=0.15)


def test_a_json_table_with_its_own_columns_bgr_frames_depths_and_balls(tmp_path):
    from scenes.dataset import read_samples
    from scenes.images import read_rgb

    folder = make_folder(tmp_path / "set", table="presses.json", columns=("image", "x", "y", "radius"),
                         no_contact="f0.jpg", bgr=True,
                         extra={"depth_mm": [0.5, 0.7, 0.9], "ball_mm": [4.0, 6.0, 4.0]})
    # the table's columns renamed: the defaults no longer find the centre
    table = json.loads((folder / "presses.json").read_text())
    (folder / "presses.json").write_text(json.dumps([{("cx" if k == "x" else k): v for k, v in r.items()}
                                                     for r in table]))
    args = ["folder", folder, "--spec", GELSIGHT, "--pixel-mm", 0.1245, "--channels", "bgr"]
    assert run(*args, "--out", tmp_path / "bad") == 1
    assert not (tmp_path / "bad").exists()
    assert run(*args, "--columns", "x=cx", "--out", tmp_path / "cap") == 0
    records = read_samples(tmp_path / "cap")
    assert [r["measured_depth"] for r in records] == pytest.approx([0.5e-3, 0.7e-3, 0.9e-3])
    assert [r["object"] for r in records] == ["ball_4mm", "ball_6mm", "ball_4mm"]
    assert all(r["depth_source"] == "given" for r in records)
    meta = json.loads((tmp_path / "cap" / "dataset.json").read_text())
    assert meta["import"]["depth"] == "given" and meta["protocol"]["objects"] == ["ball_4mm", "ball_6mm"]
    assert meta["renderer"]["camera"]["channels"] == "stored BGR, turned to RGB"
    # the JPEG's red, stored third, is read back first (JPEG keeps a flat grey to a few levels)
    assert read_rgb(tmp_path / "cap" / "background.png")[60, 80, 0] == pytest.approx(0.6, abs=0.02)


def test_a_sets_records_name_the_whole_set(tmp_path, capsys):
    folder = make_folder(tmp_path / "set", records='name = "made here"\nspec = "gelsight"\nball_mm = 4.0\n'
                                                  'pixel_mm = 0.1245\n')
    assert run("folder", folder, "--out", tmp_path / "cap") == 0
    out = capsys.readouterr().out
    assert "ball_mm from records" in out and "spec from records" in out and "ball_4mm" in out
    meta = json.loads((tmp_path / "cap" / "dataset.json").read_text())
    assert meta["import"]["pixel_mm"] == pytest.approx(0.1245) and meta["sensor"]["name"] == "gelsight"
    # the command line wins over the records
    assert run("folder", folder, "--out", tmp_path / "cap6", "--ball-mm", 6) == 0
    assert "ball_6mm" in capsys.readouterr().out
    (folder / "set.toml").write_text("ball_mm = 4.0\nball_size = 4\n")
    assert run("folder", folder, "--out", tmp_path / "bad") == 1
    assert "unknown keys ['ball_size']" in capsys.readouterr().err
    assert not (tmp_path / "bad").exists()


def test_the_two_formats_give_the_same_capture(tmp_path):
    """A Taxim pack, and the same presses written as a folder, import to the same capture:
    every file byte for byte, dataset.json but for where each came from."""
    from scenes.spec_read import load_spec

    from tests.test_import_capture import write_pack

    pack = press_sets.read_taxim(write_pack(tmp_path / "dataPack_small.npz"))
    folder = press_sets.read_folder(press_sets.write_folder(pack, tmp_path / "set"))
    assert folder.names == pack.names
    np.testing.assert_array_equal(folder.frames, pack.frames)
    for archive, out, fmt in ((pack, "a", "taxim"), (folder, "b", "folder")):
        imports.import_capture(archive, tmp_path / out, load_spec(GELSIGHT), 4e-3, 0.1245e-3, fmt=fmt)
    files = sorted(p.relative_to(tmp_path / "a") for p in (tmp_path / "a").rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(tmp_path / "b") for p in (tmp_path / "b").rglob("*") if p.is_file())
    assert len(files) == 3 + 4  # an image a press; dataset, protocol, samples, background
    for f in files:
        if f.name != "dataset.json":
            assert (tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes(), f

    def stripped(path):
        meta = json.loads(path.read_text())
        for key in ("format", "archive", "sha256"):
            meta["import"].pop(key)
        meta["renderer"]["camera"] = {"kind": meta["renderer"]["camera"]["kind"]}
        return meta

    assert stripped(tmp_path / "a" / "dataset.json") == stripped(tmp_path / "b" / "dataset.json")


# --- bad input: one clear line each, nothing written -------------------------------------------


def _without_image(folder):
    (folder / "press_1.png").unlink()


def _wrong_size(folder):
    Image.new("RGB", (150, 120)).save(folder / "press_2.png")


def _no_centre_columns(folder):
    text = (folder / "presses.csv").read_text().replace("image,x,y,radius", "image,u,v,radius")
    (folder / "presses.csv").write_text(text)


def _centre_outside(folder):
    text = (folder / "presses.csv").read_text().replace("110.0,40.0", "170.0,40.0")
    (folder / "presses.csv").write_text(text)


def _no_background(folder):
    (folder / "background.png").unlink()


@pytest.mark.parametrize("spoil, message", [
    (_without_image, r"press 1 \(press_1\.png\): its image .*press_1\.png is missing"),
    (_wrong_size, r"press 2 \(press_2\.png\): its image is 150x120 px, the no-contact frame background\.png "
                  r"160x120 px; every frame must be the same size"),
    (_no_centre_columns, r"press table .*presses\.csv has no column for x \('x'\), y \('y'\): each press needs its "
                         r"image, its centre"),
    (_centre_outside, r"press 2 \(press_2\.png\): its centre \(170, 40\) px lies outside the 160x120 frame"),
    (_no_background, r"folder .*set has no no-contact frame \(looked for background\.png, no_contact\.png"),
])
def test_bad_folders_are_refused_in_one_line_and_nothing_is_written(tmp_path, capsys, spoil, message):
    import re

    folder = make_folder(tmp_path / "set")
    spoil(folder)
    assert run("folder", folder, "--out", tmp_path / "cap", "--spec", GELSIGHT, "--ball-mm", 4) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("tactile-sim import: error: ")
    assert re.search(message, err), err
    assert not (tmp_path / "cap").exists()


def test_a_press_without_a_ball_or_depth_is_refused(tmp_path, capsys):
    folder = make_folder(tmp_path / "set")
    assert run("folder", folder, "--out", tmp_path / "cap", "--spec", GELSIGHT) == 1
    assert "press 0 (press_0.png) has no ball diameter in its table and none was given (--ball-mm" in \
        capsys.readouterr().err
    assert run("folder", folder, "--out", tmp_path / "cap", "--spec", GELSIGHT, "--ball-mm", 4,
               "--depth", "given") == 1
    assert "records no depth; --depth given takes every press's depth from its table" in capsys.readouterr().err
    assert run("taxim", folder, "--out", tmp_path / "cap", "--table", "presses.csv") == 1
    assert "table: options of the folder format, not of a Taxim pack" in capsys.readouterr().err
    assert not (tmp_path / "cap").exists()


def test_a_spec_by_name_or_by_its_capture(tmp_path):
    from scenes.spec_read import load_spec, spec_file

    assert spec_file("digit").name == "digit.toml" and load_spec("gelsight_mini").name == "gelsight_mini"
    assert spec_file("no_such_sensor") == Path("no_such_sensor")  # not a shipped one: a path, refused on reading
    folder = make_folder(tmp_path / "set", shape=(160, 120), centres=[(c[1], c[0]) for c in CENTRES])
    assert run("folder", folder, "--out", tmp_path / "cap", "--spec", "gelsight", "--ball-mm", 4) == 0
    unit = load_spec(tmp_path / "cap")  # the unit's own camera, as its capture records it
    assert (unit.camera.width, unit.camera.height) == (120, 160)
    with pytest.raises(ValueError, match=r"a folder must be a dataset whose dataset.json records its sensor"):
        load_spec(folder)


def test_a_taxim_pack_reads_its_records_beside_it(tmp_path, capsys):
    from tests.test_import_capture import write_pack

    pack = write_pack(tmp_path / "dataPack_small.npz")
    assert press_sets.guess_format(pack) == "taxim" and press_sets.guess_format(tmp_path) == "taxim"
    (tmp_path / "dataPack_small.toml").write_text('spec = "gelsight"\nball_mm = 6.0\n')
    assert run("taxim", pack, "--out", tmp_path / "cap") == 0
    out = capsys.readouterr().out
    assert "ball_6mm" in out and "ball_mm from records" in out and "pixel_mm from the taxim set's default" in out
    (tmp_path / "dataPack_small.toml").write_text('format = "folder"\n')
    assert run("taxim", pack, "--out", tmp_path / "bad") == 1
    assert "say the archive is 'folder', not 'taxim'" in capsys.readouterr().err
