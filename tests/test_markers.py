"""Printed marker dots: found and filled (scenes.markers), on frames made here, and the
folder importer's --markers inpaint."""

from __future__ import annotations

import numpy as np
import pytest

from scenes import imports, markers, press_sets
from studies.markers import draw_markers

PIXEL_M = 0.1245e-3


def smooth_press(shape=(120, 160), centre=(80.0, 60.0), rim_px=13.5):
    """A lit frame (a smooth gradient per channel) and a ring press on it: (no_contact, frame)."""
    v, u = np.mgrid[: shape[0], : shape[1]]
    f0 = np.stack([0.3 + 0.3 * u / shape[1], 0.5 - 0.2 * v / shape[0], 0.4 + 0.1 * np.sin(u / 30.0)], axis=-1)
    r = np.hypot(u - centre[0], v - centre[1])
    return f0, np.clip(f0 + 0.2 * np.exp(-0.5 * ((r - rim_px) / 3.0) ** 2)[..., None], 0, 1)


def archive_of(f0, frame, centre=(80.0, 60.0)):
    return press_sets.Archive(no_contact=f0, frames=frame[None], centres_px=np.array([centre]),
                           radii_px=np.array([17.0]), names=("p",), path="made here")


def test_dots_are_found_where_they_are_drawn_and_not_on_a_press():
    f0, frame = smooth_press()
    dotted = draw_markers(archive_of(f0, frame), PIXEL_M)
    changed = np.abs(dotted.frames[0] - frame).max(axis=2) > 0.02
    mask = markers.marker_mask(dotted.frames[0], markers.DOT_M / PIXEL_M)
    assert mask[changed].mean() > 0.99  # every dot's pixel is masked
    assert mask.mean() < 2.5 * changed.mean()  # and little else, its edge grown by a pixel
    assert not markers.marker_mask(frame, markers.DOT_M / PIXEL_M).any()  # the press alone has none


def test_filled_dots_give_back_the_frame_and_its_rim():
    f0, frame = smooth_press()
    dotted = draw_markers(archive_of(f0, frame), PIXEL_M)
    clean_f0, clean, report = markers.remove_markers(dotted.no_contact, dotted.frames, PIXEL_M)
    assert np.abs(dotted.frames[0] - frame).mean() > 0.02
    assert np.abs(clean[0] - frame).mean() < 0.002 and np.abs(clean_f0 - f0).mean() < 0.002
    assert 0.05 < report["no_contact_share"] < 0.4
    rim = imports.contact_edge_px(frame, f0, (80.0, 60.0), 2e-3 / PIXEL_M)
    assert imports.contact_edge_px(clean[0], clean_f0, (80.0, 60.0), 2e-3 / PIXEL_M) == pytest.approx(rim, abs=0.25)
    # kept, the dots moved by the press shift the rim the import finds
    kept = imports.contact_edge_px(dotted.frames[0], dotted.no_contact, (80.0, 60.0), 2e-3 / PIXEL_M)
    assert abs(kept - rim) > abs(imports.contact_edge_px(clean[0], clean_f0, (80.0, 60.0), 2e-3 / PIXEL_M) - rim)


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError, match=r"image must be \(H, W, 3\), got \(4, 4\)"):
        markers.marker_mask(np.zeros((4, 4)), 5.0)
    with pytest.raises(ValueError, match=r"a dot's size must be at least a pixel, got 0.5 px"):
        markers.marker_mask(np.zeros((4, 4, 3)), 0.5)


def test_the_import_fills_the_dots_and_records_it(tmp_path, capsys):
    import json

    from PIL import Image

    from scenes.cli import main

    f0, frame = smooth_press()
    dotted = draw_markers(archive_of(f0, frame), PIXEL_M)
    folder = tmp_path / "set"
    folder.mkdir()
    Image.fromarray((dotted.no_contact * 255).round().astype(np.uint8)).save(folder / "background.png")
    Image.fromarray((dotted.frames[0] * 255).round().astype(np.uint8)).save(folder / "p.png")
    (folder / "presses.csv").write_text("image,x,y,radius\np.png,80,60,17\n")
    args = ["import", "folder", str(folder), "--spec", "gelsight", "--ball-mm", "4", "--pixel-mm", "0.1245"]
    assert main([*args, "--markers", "inpaint", "--out", str(tmp_path / "cap")]) == 0
    assert "marker dots inpainted" in capsys.readouterr().out
    meta = json.loads((tmp_path / "cap" / "dataset.json").read_text())
    assert meta["import"]["markers"]["method"].startswith("black top-hat")
    from scenes.images import read_rgb

    assert np.abs(read_rgb(tmp_path / "cap" / "background.png") - f0).mean() < 0.004
    assert main([*args, "--out", str(tmp_path / "kept")]) == 0
    assert json.loads((tmp_path / "kept" / "dataset.json").read_text())["import"]["markers"] == "kept"
