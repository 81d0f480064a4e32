"""Datasets: the format's writer and reader, and generation that survives being killed."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from scenes.dataset import (
    DatasetError,
    DatasetWriter,
    load_sample,
    read_meta,
    read_samples,
    write_sample_files,
)

META = {"source": "sim", "sensor": {"name": "x"}, "protocol": {"name": "base"}, "renderer": {"renderer": "phong"}}


def _sample(writer, sid, value=0.5):
    files = write_sample_files(writer.root, sid, np.full((4, 6, 3), value), np.full((4, 6), 0.03))
    writer.append({"id": sid, **files})


def test_writer_resumes_and_refuses_other_settings(tmp_path):
    w = DatasetWriter(tmp_path, META, protocol={"taps": []})
    _sample(w, "a")
    _sample(w, "b")
    assert read_meta(tmp_path)["format"] == "tactile-sim-dataset"
    assert json.loads((tmp_path / "protocol.json").read_text()) == {"taps": []}
    again = DatasetWriter(tmp_path, META, protocol={"taps": []})
    assert again.done == {"a", "b"}
    with pytest.raises(DatasetError, match="already in"):
        _sample(again, "a")
    with pytest.raises(DatasetError, match="different renderer"):
        DatasetWriter(tmp_path, {**META, "renderer": {"renderer": "pbr"}}, protocol={"taps": []})
    with pytest.raises(DatasetError, match="different protocol"):
        DatasetWriter(tmp_path, META, protocol={"taps": [1]})
    image, depth = load_sample(tmp_path, read_samples(tmp_path)[0], (4, 6))
    assert image.shape == (4, 6, 3) and depth.shape == (4, 6)


def test_a_line_cut_short_is_dropped_and_repaired(tmp_path):
    w = DatasetWriter(tmp_path, META)
    _sample(w, "a")
    with open(tmp_path / "samples.jsonl", "a") as fh:
        fh.write('{"id": "b", "ima')  # killed mid-write
    (tmp_path / "images" / ".b.png.123.tmp").write_bytes(b"partial")
    w2 = DatasetWriter(tmp_path, META)
    assert w2.done == {"a"}
    assert not list((tmp_path / "images").glob(".*.tmp"))
    _sample(w2, "b")
    assert [r["id"] for r in read_samples(tmp_path)] == ["a", "b"]


def test_extra_arrays_are_written_beside_the_image(tmp_path):
    w = DatasetWriter(tmp_path, META)
    image = np.full((4, 6, 3), 0.5)
    arrays = {"linear": np.ones((4, 6, 3)), "variance": np.full((4, 6, 3), 1e-4)}
    files = write_sample_files(tmp_path, "a", image, None, arrays)
    assert files == {"image": "images/a.png", "linear": "linear/a.npy", "variance": "variance/a.npy"}
    w.append({"id": "a", **files})
    linear = np.load(tmp_path / read_samples(tmp_path)[0]["linear"])
    assert linear.dtype == np.float32 and linear.shape == (4, 6, 3)
    for bad in ("depth", "images", "../up", "Linear", 3):
        with pytest.raises(ValueError, match="array name must match"):
            write_sample_files(tmp_path, "b", image, None, {bad: arrays["linear"]})
    files = write_sample_files(tmp_path, "c", image, None)
    with pytest.raises(DatasetError, match="sample c: linear/c.npy was not written"):
        w.append({"id": "c", **files, "linear": "linear/c.npy"})
    (tmp_path / "linear" / ".c.npy.123.tmp").write_bytes(b"partial")  # killed mid-write
    DatasetWriter(tmp_path, META)
    assert not list(tmp_path.glob("*/.*.tmp"))


def test_corrupt_datasets_are_named(tmp_path):
    with pytest.raises(DatasetError, match="dataset.json is missing"):
        read_meta(tmp_path)
    (tmp_path / "dataset.json").write_text("{not json")
    with pytest.raises(DatasetError, match="corrupt"):
        read_meta(tmp_path)
    (tmp_path / "dataset.json").write_text(json.dumps({"format": "other"}))
    with pytest.raises(DatasetError, match="not a tactile-sim-dataset"):
        read_meta(tmp_path)
    (tmp_path / "samples.jsonl").write_text('{"id": "a"}\ngarbage\n{"id": "c"}\n')
    with pytest.raises(DatasetError, match="line 2"):
        read_samples(tmp_path)
    (tmp_path / "samples.jsonl").write_text('{"id": "a"}\n{"id": "a"}\n')
    with pytest.raises(DatasetError, match="appears twice"):
        read_samples(tmp_path)
    with pytest.raises(DatasetError, match="image images/zz.png is missing"):
        load_sample(tmp_path, {"id": "zz", "image": "images/zz.png"})
    with pytest.raises(ValueError, match="source"):
        DatasetWriter(tmp_path / "new", {**META, "source": "dream"})



def _cli(*args):
    return [sys.executable, "-m", "scenes.cli", *args]


def test_generation_killed_midway_resumes_with_nothing_lost_or_duplicated(tmp_path, headless_gl):
    out = tmp_path / "ds"
    args = _cli("dataset", "--protocol", "base", "--objects", "sphere,cone", "--workers", "2", "--out", str(out))
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.time() + 120
    lines = 0
    while time.time() < deadline and proc.poll() is None:
        path = out / "samples.jsonl"
        lines = path.read_text().count("\n") if path.exists() else 0
        if lines >= 6:
            break
        time.sleep(0.05)
    assert proc.poll() is None, "the run finished before it could be killed; make the dataset larger"
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    first = read_samples(out)
    assert 6 <= len(first) < 36
    res = subprocess.run(args, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    records = read_samples(out)
    ids = [r["id"] for r in records]
    assert len(ids) == 36 and len(set(ids)) == 36
    assert ids[: len(first)] == [r["id"] for r in first]  # nothing rewritten
    meta = read_meta(out)
    assert meta["protocol"]["taps"] == 36 and meta["source"] == "sim"
    assert (out / "background.png").exists()
    for record in records:
        image, depth = load_sample(out, record, (480, 640))
        assert depth.shape == (480, 640)
        assert record["measured_depth"] == pytest.approx(record["commanded_depth"], abs=0.05e-3)
    assert not list(out.rglob(".*.tmp"))


def test_dataset_bad_input(tmp_path, headless_gl):
    from scenes.cli import main

    assert main(["dataset", "--objects", "teapot", "--out", str(tmp_path / "a"), "--workers", "1"]) == 1
    res = subprocess.run(_cli("dataset", "--objects", "teapot", "--out", str(tmp_path / "a")), capture_output=True, text=True)
    assert res.returncode == 1 and "must be one of" in res.stderr and "teapot" in res.stderr
    res = subprocess.run(_cli("dataset", "--objects", "sphere", "--field", "spline", "--out", str(tmp_path / "b")),
                         capture_output=True, text=True)
    assert res.returncode == 1 and "field must be one of" in res.stderr


def test_dataset_quiet_turns_the_progress_bar_off(tmp_path, headless_gl, capsys):
    from scenes.cli import main

    argv = ["dataset", "--objects", "sphere", "--limit", "1", "--workers", "1", "--field", "plane"]
    assert main([*argv, "--out", str(tmp_path / "loud")]) == 0
    assert "sample/s" in capsys.readouterr().err  # tqdm's bar, so that the check below means something
    assert main([*argv, "--quiet", "--out", str(tmp_path / "quiet")]) == 0
    out = capsys.readouterr()
    assert out.err == "" and out.out.startswith("1 samples in ")


def test_scene_commands(tmp_path, headless_gl):
    from scenes.cli import main
    from scenes.images import read_rgb

    png = tmp_path / "rig.png"
    assert main(["scene", "snapshot", "-o", str(png), "--width", "320", "--height", "240", "--object", "cone"]) == 0
    assert read_rgb(png).std() > 0.05
    assert main(["scene", "export", "-o", str(tmp_path / "xml"), "--object", "all"]) == 0
    xml = (tmp_path / "xml" / "rig.xml").read_text()
    assert 'name="geltip_depth"' in xml and 'name="indenter_pacman"' in xml


@pytest.mark.slow
def test_bench_dataset_writes_json(tmp_path, headless_gl):
    from scenes.cli import main

    out = tmp_path / "bench.json"
    assert main(["bench", "dataset", "--json", str(out), "--workers", "1"]) == 0
    data = json.loads(out.read_text())
    assert data["samples"] == 144 and data["frames_per_second"] > 0 and data["ms_per_depth_frame"] > 0
