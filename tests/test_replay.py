"""Replay of a capture: its taps rendered at the rig's measured poses, the same protocol and
sample ids, so that diagnose pairs them; and every way a capture can be unfit for it."""

from __future__ import annotations

import json
import shutil
import sys

import numpy as np
import pytest

from scenes.dataset import DatasetError, read_meta, read_samples

#: Largest pixel difference, a fraction of full scale, that a contact moved by the
#: perturbation exceeds in every tap (sub-millimetre moves at 80x60: a few pixels change).
MOVED = 8 / 255


def _mae(a, b) -> float:
    return float(np.abs(np.asarray(a, np.float64) - b).mean())


def test_replay_of_a_fast_path_capture_reproduces_it(tiny_capture, tiny_replay):
    """A capture made by the fast path, replayed by it with the same settings at the same
    poses, gives the same images bit for bit, under the same ids and protocol."""
    from tests.fake_capture import images

    capture, sim = read_samples(tiny_capture), read_samples(tiny_replay)
    assert [r["id"] for r in sim] == [r["id"] for r in capture]
    assert _mae(images(tiny_capture), images(tiny_replay)) == 0.0
    for c, s in zip(capture, sim):
        assert s["pose"] == c["measured_pose"] and s["tap_index"] == c["tap_index"]
        assert s["measured_depth"] == pytest.approx(c["measured_depth"], abs=1e-9)
        assert s["depth"] == f"depth/{s['id']}.npy"
    real_meta, sim_meta = read_meta(tiny_capture), read_meta(tiny_replay)
    assert sim_meta["protocol"] == real_meta["protocol"]  # name, sha256: what diagnose pairs by
    assert sim_meta["source"] == "sim" and sim_meta["replay"]["pose"] == "measured_pose"
    assert (tiny_replay / "protocol.json").read_bytes() == (tiny_capture / "protocol.json").read_bytes()


def test_diagnose_pairs_a_capture_with_its_replay(diagnose_report):
    report = json.loads((diagnose_report / "report.json").read_text())
    assert report["pairs"] == 4
    assert report["gap"]["all"]["masked"]["mae"]["mean"] == 0.0
    # each held-out tap's contact region is judged too (where the real tap differs from its background)
    assert report["gap_contact"]["mae"]["mean"] == 0.0
    assert "contact" in report["effects"]["camera_response"]["share_closed"]


def test_replay_sets_the_measured_pose_not_the_commanded_one(tmp_path, tiny_spec, session_env):
    """With measured poses off the commanded ones by a known perturbation, the replay
    reproduces the capture; replaying the commanded poses instead does not."""
    from phong_reference import plugin as phong
    from scenes.geometry import membrane_mesh
    from scenes.replay import replay
    from tests.fake_capture import PERTURBATION, capture_protocol, edit_samples, images, write_capture

    protocol = capture_protocol(tiny_spec, membrane_mesh(tiny_spec))
    root = write_capture(tmp_path / "capture", tiny_spec, protocol, perturbation=PERTURBATION)
    options = {"field": "plane", "background": "solid"}
    replay(root, tmp_path / "measured", phong, options, progress=False)
    assert _mae(images(root), images(tmp_path / "measured")) == 0.0
    commanded = shutil.copytree(root, tmp_path / "commanded")
    edit_samples(commanded, lambda r: {**r, "measured_pose": r["commanded_pose"]})
    replay(commanded, tmp_path / "at_commanded", phong, options, progress=False)
    moved = np.abs(images(root) - images(tmp_path / "at_commanded")).max(axis=(1, 2, 3))
    assert (moved > MOVED).all(), moved * 255


def test_replay_never_opens_the_virtual_rigs_hidden_settings(tiny_capture, tmp_path):
    from phong_reference import plugin as phong
    from scenes.replay import replay
    from tests.fake_capture import HIDDEN

    opened = []
    watching = [True]

    def hook(event, args):
        if watching[0] and event == "open" and str(args[0]).endswith(HIDDEN):
            opened.append(args[0])

    sys.addaudithook(hook)  # hooks cannot be removed: this one is switched off below
    try:
        assert (tiny_capture / HIDDEN).exists()
        replay(tiny_capture, tmp_path / "sim", phong, {"field": "plane", "background": "solid"},
               ids=[read_samples(tiny_capture)[0]["id"]], progress=False)
    finally:
        watching[0] = False
    assert opened == []


def _broken(tiny_capture, tmp_path, edit=None, meta=None):
    root = shutil.copytree(tiny_capture, tmp_path / "capture")
    if edit is not None:
        from tests.fake_capture import edit_samples

        edit_samples(root, edit)
    if meta is not None:
        path = root / "dataset.json"
        path.write_text(json.dumps(meta(json.loads(path.read_text()))))
    return root


def _without(key):
    def edit(record):
        if record["tap_index"] == 2:
            record["measured_pose"] = {k: v for k, v in record["measured_pose"].items() if k != key}
        return record
    return edit


@pytest.mark.parametrize("case, expected", [
    ("no dataset.json", r"capture .* is not a dataset: dataset\.json is missing"),
    ("no protocol.json", r"capture .*: protocol\.json is missing; a replay takes each sample's tap from it"),
    ("not real", r"capture .*: source is 'sim'; a replay takes a capture of the rig \(source 'real'\)"),
    ("no measured_pose", r"sample 000001_sphere \(samples\.jsonl line 2\) has no measured_pose"),
    ("pose lacks a joint", r"sample 000002_cylinder \(samples\.jsonl line 3\): measured_pose lacks printer_z; "
                           r"expected exactly the rig's joints"),
    ("pose not a number", r"sample 000000_sphere .*: measured_pose\.sensor_roll must be a finite number"),
    ("wrong object", r"sample 000003_cylinder .*: object 'sphere' and id '000003_cylinder' disagree with "
                     r"protocol\.json tap 3 \('cylinder', id 000003_cylinder\)"),
    ("wrong tap_index", r"sample 000000_sphere .*: object 'sphere' and id '000000_sphere' disagree with "
                        r"protocol\.json tap 2 \('cylinder', id 000002_cylinder\)"),
    ("tap_index out of range", r"sample 000000_sphere .*: tap_index 9 is not a tap of protocol\.json \(0 to 3\)"),
])
def test_replay_refuses_unfit_captures(tiny_capture, tmp_path, case, expected):
    from scenes.replay import read_capture

    edits = {
        "no measured_pose": (lambda r: {k: v for k, v in r.items() if k != "measured_pose"}
                             if r["tap_index"] == 1 else r),
        "pose lacks a joint": _without("printer_z"),
        "pose not a number": (lambda r: {**r, "measured_pose": {**r["measured_pose"], "sensor_roll": "0.1"}}
                              if r["tap_index"] == 0 else r),
        "wrong object": lambda r: {**r, "object": "sphere"} if r["tap_index"] == 3 else r,
        "wrong tap_index": lambda r: {**r, "tap_index": 2} if r["id"] == "000000_sphere" else r,
        "tap_index out of range": lambda r: {**r, "tap_index": 9} if r["id"] == "000000_sphere" else r,
    }
    root = _broken(tiny_capture, tmp_path, edits.get(case),
                   (lambda m: {**m, "source": "sim"}) if case == "not real" else None)
    if case == "no dataset.json":
        (root / "dataset.json").unlink()
    if case == "no protocol.json":
        (root / "protocol.json").unlink()
    with pytest.raises(DatasetError, match=expected):
        read_capture(root)


def test_replay_names_the_sample_whose_pose_is_out_of_travel(tiny_capture, tmp_path):
    from phong_reference import plugin as phong
    from scenes.replay import replay

    root = _broken(tiny_capture, tmp_path, lambda r: {**r, "measured_pose": {**r["measured_pose"], "printer_z": 9.0}}
                   if r["tap_index"] == 1 else r)
    with pytest.raises(ValueError, match=r"sample 000001_sphere: pose: printer_z = 9 is outside its travel"):
        replay(root, tmp_path / "sim", phong, {"field": "plane"}, progress=False)


def test_replay_takes_a_renderer_plugin_not_its_name(tiny_capture, tmp_path):
    """Only the command line looks a renderer up by name (``scenes.renderers.get_renderer``)."""
    from scenes.replay import replay

    with pytest.raises(ValueError, match=r"renderer must be a renderer plugin .*got the name 'phong'"):
        replay(tiny_capture, tmp_path / "sim", "phong", {"field": "plane"}, progress=False)
    assert not (tmp_path / "sim").exists()  # refused before any work


def test_dataset_command_takes_replay_or_a_protocol_not_both(tiny_capture, tmp_path, capsys):
    from scenes.cli import main

    assert main(["dataset", "--replay", str(tiny_capture), "--protocol", "base", "--objects", "sphere",
                 "--out", str(tmp_path / "x")]) == 1
    err = capsys.readouterr().err
    assert "--replay takes the sensor and the taps from CAPTURE_DIR" in err and "drop --protocol, --objects" in err
    assert main(["dataset", "--replay", str(tmp_path / "nowhere"), "--out", str(tmp_path / "x")]) == 1
    assert "is not a dataset: dataset.json is missing" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()
