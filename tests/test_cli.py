"""The tactile-sim command line, run as a user would."""

import json
import subprocess
import sys

import numpy as np
import pytest

from scenes.cli import main
from scenes.images import read_rgb


def run(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "scenes.cli", *args], capture_output=True, text=True, cwd=cwd)


def test_help_lists_every_subcommand():
    out = run("--help").stdout
    for name in ("demo", "bake", "render", "bench"):
        assert name in out
    bench = run("bench", "--help").stdout
    assert "phong" in bench and "bake" in bench


def test_render_a_depth_map(tmp_path, camera, mesh):
    from scenes.camera import reference_depth

    ref, _ = reference_depth(mesh, camera)
    depth = ref.copy()
    depth[200:220, 300:330] -= 0.001
    np.save(tmp_path / "d.npy", depth)
    out = tmp_path / "img.png"
    assert main(["render", str(tmp_path / "d.npy"), "--field", "linear", "--background", "solid", "-o", str(out)]) == 0
    image = read_rgb(out, (480, 640))
    assert image[camera.mask].mean() > 0.1 and not image[~camera.mask].any()


def test_render_refuses_bad_depth_files(tmp_path, capsys):
    np.save(tmp_path / "small.npy", np.ones((120, 160), np.float32) * 0.03)
    assert main(["render", str(tmp_path / "small.npy"), "--field", "linear", "-o", str(tmp_path / "x.png")]) == 1
    assert "must be (480, 640) float" in capsys.readouterr().err
    bad = np.ones((480, 640), np.float32) * 0.03
    bad[5, 5] = np.nan
    np.save(tmp_path / "nan.npy", bad)
    assert main(["render", str(tmp_path / "nan.npy"), "--field", "linear", "-o", str(tmp_path / "x.png")]) == 1
    assert "NaN" in capsys.readouterr().err
    (tmp_path / "junk.npy").write_bytes(b"junk")
    assert main(["render", str(tmp_path / "junk.npy"), "--field", "linear", "-o", str(tmp_path / "x.png")]) == 1
    assert "could not be read" in capsys.readouterr().err
    assert not (tmp_path / "x.png").exists()


def test_bake_any_mesh_from_the_command_line(tmp_path, mesh):
    path = tmp_path / "membrane_mm.stl"
    mm = mesh.copy()
    mm.apply_scale(1000)
    mm.export(path)
    res = run("bake", "--field", "linear", "--mesh", str(path))
    assert res.returncode == 1 and "millimetres" in res.stderr
    res = run("bake", "--field", "linear", "--mesh", str(path), "--units", "mm", "--out", str(tmp_path / "o"))
    assert res.returncode == 0, res.stderr
    assert (tmp_path / "o" / "linear_fields.png").exists()


@pytest.mark.slow
def test_bench_phong_writes_json(tmp_path):
    out = tmp_path / "b.json"
    assert main(["bench", "phong", "--json", str(out), "--frames", "2", "--repeats", "1"]) == 0
    data = json.loads(out.read_text())
    for key in ("ms_per_frame_median", "baseline_ms_per_frame_median", "speedup"):
        assert data[key] > 0


@pytest.mark.parametrize(
    "argv",
    [["demo"], ["bake"], ["render"], ["scene"], ["dataset"], ["reference"], ["bench", "phong"], ["bench", "bake"],
     ["bench", "dataset"], ["bench", "pbr"]],
)
def test_every_subcommand_prints_its_help(argv, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(argv + ["--help"])
    assert exit_info.value.code == 0
    assert "usage: tactile-sim" in capsys.readouterr().out


def test_a_device_that_does_not_open_is_one_line_not_a_traceback(tmp_path, capsys):
    argv = ["rig", "run", "--printer", "/dev/ttyUSB9", "--servos", "/dev/ttyUSB8", "--camera", "0",
            "--objects", "sphere", "--limit", "1", "--no-alignment", "--quiet", "--out", str(tmp_path / "cap")]
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert err.startswith("tactile-sim rig run: error: cannot open printer port '/dev/ttyUSB9'"), err
    assert err.count("\n") == 1 and "Traceback" not in err
    res = run(*argv)  # as a user runs it: nothing else on stderr either
    assert res.returncode == 1 and res.stderr == err and "Traceback" not in res.stderr


def test_the_project_errors_and_os_errors_are_reported_in_one_line(monkeypatch, capsys):
    from rig.servos import ServoTimeout
    from scenes import commands

    for exc in (ServoTimeout("servo board on /dev/ttyACM0 did not answer"), PermissionError(13, "Permission denied")):
        def fail(args, exc=exc):
            raise exc

        monkeypatch.setattr(commands, "cmd_scene", fail)
        assert main(["scene", "export"]) == 1
        err = capsys.readouterr().err
        assert err == f"tactile-sim scene: error: {exc}\n"


@pytest.mark.parametrize("text", ["-3", "-1", "two", "1.5", ""])
def test_a_count_refuses_what_is_not_a_whole_number_at_least_0(text):
    import argparse

    from scenes.commands import non_negative_int

    with pytest.raises(argparse.ArgumentTypeError, match=f"expected a whole number >= 0, got '{text}'"):
        non_negative_int(text)
    assert non_negative_int("0") == 0 and non_negative_int("12") == 12


@pytest.mark.parametrize("argv", [
    ["dataset", "--objects", "sphere", "--out", "OUT", "--limit", "-3"],
    ["rig", "run", "--printer", "twin", "--servos", "twin", "--camera", "twin", "--out", "OUT", "--limit", "-3"],
])
def test_a_negative_limit_is_refused_not_taken_from_the_end(argv, tmp_path, capsys):
    argv = [str(tmp_path / "out") if a == "OUT" else a for a in argv]
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    assert "argument --limit: expected a whole number >= 0, got '-3'" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("argv", [
    ["dataset", "--out", "D"],
    ["rig", "run", "--out", "D", "--dry-run"],
    ["diagnose", "REAL", "SIM", "--out", "D"],
    ["bench", "diagnose", "--json", "J"],
    ["compare", "CAPTURE", "--out", "D"],
    ["calibrate", "REAL", "--out", "D"],
    ["calibrate", "benchmark", "--json", "J"],
])
def test_every_command_with_progress_bars_takes_quiet(argv):
    from scenes.cli import build_parser

    parser = build_parser()
    assert parser.parse_args(argv).quiet is False
    assert parser.parse_args([*argv, "--quiet"]).quiet is True


@pytest.mark.parametrize("count", ["0", "-2", "1.5"])
def test_bench_real_refuses_a_count_of_reference_presses_that_is_not_a_whole_positive_number(count, tmp_path,
                                                                                              capsys):
    out = tmp_path / "real.json"
    with pytest.raises(SystemExit) as exit_info:
        main(["bench", "real", "--json", str(out), "--reference-presses", count])
    assert exit_info.value.code == 2
    assert "--reference-presses" in capsys.readouterr().err
    assert not out.exists()


def test_bench_real_takes_the_reference_presses_and_refuses_a_bad_count_before_any_work(tmp_path):
    from scenes.cli import build_parser
    from studies.real_bench import REFERENCE_PRESSES, run

    parser = build_parser()
    assert parser.parse_args(["bench", "real", "--json", "J"]).reference_presses == REFERENCE_PRESSES
    assert parser.parse_args(["bench", "real", "--json", "J", "--reference-presses", "24"]).reference_presses == 24
    with pytest.raises(ValueError, match="reference_presses must be a whole number >= 1, got 0"):
        run(tmp_path / "real.json", work=tmp_path / "work", reference_presses=0)
    assert not (tmp_path / "work").exists() and not (tmp_path / "real.json").exists()
    assert parser.parse_args(["bench", "real", "--json", "J", "--runs", "3", "--fit-layout"]).runs == 3
    with pytest.raises(ValueError, match="runs must be a whole number >= 1, got 0"):
        run(tmp_path / "real.json", work=tmp_path / "work", runs=0)
    with pytest.raises(ValueError, match="runs repeats the reference's calibration: it needs the reference"):
        run(tmp_path / "real.json", work=tmp_path / "work", runs=3, reference=False)
    with pytest.raises(ValueError, match="--no-diagnosis needs --no-localisation"):
        run(tmp_path / "real.json", work=tmp_path / "work", diagnosis_on=False)
    assert parser.parse_args(["bench", "real", "--json", "J"]).diagnosis_presses is None
    assert parser.parse_args(["bench", "real", "--json", "J", "--diagnosis-presses", "16"]).diagnosis_presses == 16
    with pytest.raises(ValueError, match="diagnosis_presses must be a whole number >= 4 .half are held out., got 3"):
        run(tmp_path / "real.json", work=tmp_path / "work", reference_diagnosis=True, diagnosis_presses=3)
    assert not (tmp_path / "work").exists() and not (tmp_path / "real.json").exists()
    args = parser.parse_args(["bench", "real", "--json", "J", "--depth", "fitted", "--no-diagnosis",
                              "--no-localisation"])
    assert args.depth == "fitted" and args.no_diagnosis


def test_bench_real_s_runs_agree_by_the_issue_s_rule():
    from studies.real_bench import _spread

    def one(r, mae):
        return {"heldout_r2": {"r": r, "g": 0.9, "b": 0.85}, "contact_mae": mae, "strength_median": 0.9}

    close = _spread([one(0.80, 0.050), one(0.82, 0.051), one(0.81, 0.052)])
    assert close["agree"] and close["heldout_r2_range"]["r"] == pytest.approx(0.02)
    assert close["contact_mae_range_share"] == pytest.approx(0.002 / 0.051)
    assert not _spread([one(0.80, 0.050), one(0.84, 0.050)])["agree"]  # red 0.04 apart
    assert not _spread([one(0.80, 0.050), one(0.80, 0.054)])["agree"]  # MAE 8 % apart
    assert _spread([one(0.8, 0.05), {"heldout_r2": None, "contact_mae": None, "strength_median": None}])["agree"] is None
