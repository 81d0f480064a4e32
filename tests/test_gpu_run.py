"""The GPU run's logic without a GPU: the no-GPU path, budgets, merging, bad input, wheels.

Nothing here renders: the sub-runs are replaced by fakes that write what a bench would.
"""

from __future__ import annotations

import json
import zipfile
from pathlib import Path

import pytest

from pbr_tactile import gpu_run, gpu_wheels
from pbr_tactile.gpu_run import Bench, Outcome, figures_of, merge, plan, run_benches
from scenes.cli import main

NO_CUDA_MESSAGE = "Mitsuba variant 'cuda_ad_spectral' cannot run here: no CUDA device"


def _forbidden_runner(*args, **kwargs):
    raise AssertionError("a bench was run")


class FakeClock:
    def __init__(self):
        self.now = 0.0

    def __call__(self):
        return self.now


def fake_runner(clock: FakeClock, plans: dict):
    """A runner that, per bench name, takes ``seconds``, writes ``result`` (if any) and
    ends with ``code`` (None: stopped at its budget, after the whole timeout)."""
    calls = []

    def runner(argv, env, timeout_s, logs):
        name = Path(logs).name
        calls.append({"name": name, "argv": argv, "env": env, "timeout_s": timeout_s})
        p = plans[name]
        seconds = timeout_s if p.get("code", 0) is None else p.get("seconds", 1.0)
        clock.now += seconds
        if p.get("result") is not None:
            Path(argv[argv.index("--json") + 1]).write_text(json.dumps(p["result"]))
        return Outcome(p.get("code", 0), seconds, tuple(p.get("stderr", ())))

    runner.calls = calls
    return runner


def test_no_gpu_exits_zero_and_runs_nothing(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(gpu_run, "variant_problem", lambda variant: NO_CUDA_MESSAGE)
    monkeypatch.setattr(gpu_run, "run_command", _forbidden_runner)
    monkeypatch.setattr(gpu_run, "device_name", _forbidden_runner)
    out = tmp_path / "gpu.json"
    assert main(["gpu", "run", "--json", str(out)]) == 0
    printed = capsys.readouterr().out.strip().splitlines()
    assert len(printed) == 1 and "no CUDA device" in printed[0] and "nothing was run" in printed[0]
    assert not out.exists()


def test_no_gpu_here_for_real(tmp_path, monkeypatch, capsys):
    """The real check, where Mitsuba is installed and there is no GPU (else skipped)."""
    problem = gpu_run.variant_problem(gpu_run.GPU_VARIANT)
    if problem is None:
        pytest.skip("a CUDA device is here: this test is of the path without one")
    if gpu_run.NO_CUDA not in problem:
        pytest.skip(f"the variant cannot be checked here: {problem}")
    monkeypatch.setattr(gpu_run, "run_command", _forbidden_runner)
    assert main(["gpu", "run", "--json", str(tmp_path / "gpu.json")]) == 0
    assert "no CUDA device" in capsys.readouterr().out


def test_other_variant_problem_is_an_error(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(gpu_run, "variant_problem", lambda variant: "Mitsuba 3 is not installed")
    monkeypatch.setattr(gpu_run, "run_command", _forbidden_runner)
    assert main(["gpu", "run", "--json", str(tmp_path / "gpu.json")]) == 1
    assert "Mitsuba 3 is not installed" in capsys.readouterr().err


def test_run_writes_one_json_with_every_bench(tmp_path, monkeypatch):
    clock = FakeClock()
    runner = fake_runner(clock, {
        "dataset_rse_0.05": {"seconds": 50, "result": {"frames_per_hour": 900.0, "contact_rse_median": 0.04,
                                                        "local": {"render_seconds_median": 3.5}, "other": 1}},
        "pbr": {"code": 1, "stderr": ("Traceback", "RuntimeError: boom")},
        "calibrate": {"seconds": 60, "result": {"median_relative_error": 0.07, "seconds_per_case": 55.0}},
    })
    monkeypatch.setattr(gpu_run, "variant_problem", lambda variant: None)
    monkeypatch.setattr(gpu_run, "device_name", lambda variant: "Fake GPU")
    monkeypatch.setattr(gpu_run, "run_benches", lambda *a, **k: run_benches(*a, **k, runner=runner, clock=clock))
    out = tmp_path / "gpu.json"
    assert main(["gpu", "run", "--json", str(out), "--rse", "0.05"]) == 0
    data = json.loads(out.read_text())
    assert data["variant"] == "cuda_ad_spectral" and data["device"] == "Fake GPU"
    assert "commit" in data
    benches = data["benches"]
    assert list(benches) == ["dataset_rse_0.05", "pbr", "calibrate"]
    ds = benches["dataset_rse_0.05"]
    assert ds["status"] == "ok" and ds["seconds"] == 50 and ds["variant"] == "cuda_ad_spectral"
    assert ds["figures"] == {"frames_per_hour": 900.0, "contact_rse_median": 0.04, "local.render_seconds_median": 3.5}
    assert benches["pbr"]["status"] == "failed" and benches["pbr"]["reason"] == "exit status 1"
    assert benches["pbr"]["stderr_tail"][-1] == "RuntimeError: boom"
    assert benches["calibrate"]["figures"]["median_relative_error"] == 0.07
    # each sub-run: the variant set, a cache of its own, the bench's JSON path
    envs = [c["env"] for c in runner.calls]
    assert {e["TACTILE_SIM_MI_VARIANT"] for e in envs} == {"cuda_ad_spectral"}
    assert len({e["TACTILE_SIM_CACHE"] for e in envs}) == 3
    assert runner.calls[0]["argv"][1:5] == ["-m", "scenes.cli", "bench", "dataset"]


def test_budget_marks_stopped_and_skipped_benches(tmp_path):
    clock = FakeClock()
    benches = [Bench("a", ("bench", "a"), 100.0, "pbr"), Bench("b", ("bench", "b"), 100.0, "pbr"),
               Bench("c", ("bench", "c"), 100.0, "calibrate"), Bench("d", ("bench", "d"), 100.0, "pbr")]
    runner = fake_runner(clock, {
        "a": {"seconds": 60, "result": {"seconds_to_2pct": 12.0}},
        "b": {"code": None, "result": None, "stderr": ("rendering: 40%",)},
        # c is stopped by what is left of the run's budget, with the cases it wrote kept
        "c": {"code": None, "result": {"median_relative_error": 0.1, "cases": 1}},
        "d": {"seconds": 1},
    })
    entries = run_benches(benches, "cuda_ad_spectral", "Fake GPU", tmp_path, budget_s=200.0, runner=runner, clock=clock)
    assert list(entries) == ["a", "b", "c", "d"]
    assert entries["a"]["status"] == "ok" and entries["a"]["figures"] == {"seconds_to_2pct": 12.0}
    assert entries["b"]["status"] == "failed" and "its budget" in entries["b"]["reason"]
    assert entries["b"]["seconds"] == 100.0 and entries["b"]["stderr_tail"] == ["rendering: 40%"]
    assert entries["c"]["status"] == "failed" and "run's budget" in entries["c"]["reason"]
    assert runner.calls[2]["timeout_s"] == 40.0  # 200 - 60 - 100
    assert entries["c"]["figures"] == {"median_relative_error": 0.1, "cases": 1}
    assert entries["d"]["status"] == "skipped" and "budget" in entries["d"]["reason"]
    assert entries["d"]["seconds"] is None
    assert [c["name"] for c in runner.calls] == ["a", "b", "c"]


def test_a_bench_that_writes_no_json_failed(tmp_path):
    clock = FakeClock()
    runner = fake_runner(clock, {"a": {"seconds": 5}})
    entries = run_benches([Bench("a", ("bench", "a"), 50.0, "pbr")], "cuda_ad_spectral", "G", tmp_path,
                          runner=runner, clock=clock)
    assert entries["a"]["status"] == "failed" and "no readable JSON" in entries["a"]["reason"]


def test_run_command_stops_at_its_budget(tmp_path):
    import sys

    outcome = gpu_run.run_command([sys.executable, "-c", "import sys, time; print('started', file=sys.stderr, "
                                   "flush=True); time.sleep(30)"], {}, 1.0, tmp_path / "slow")
    assert outcome.returncode is None and outcome.seconds < 15
    assert outcome.stderr_tail == ("started",)
    done = gpu_run.run_command([sys.executable, "-c", "raise SystemExit(3)"], {}, 10.0, tmp_path / "quick")
    assert done.returncode == 3


def _run_json(variant, commit, benches):
    return {"variant": variant, "device": f"{variant} device", "commit": commit, "benches": benches}


def test_merge_puts_cpu_beside_gpu(tmp_path):
    gpu = _run_json("cuda_ad_spectral", "abc", {
        "pbr": {"status": "ok", "figures": {"seconds_to_2pct": 2.0, "variant": "cuda_ad_spectral", "speedup": 10.0}},
        "calibrate": {"status": "failed", "figures": {"seconds_per_case": 30.0}},
        "dataset_rse_0.05": {"status": "ok", "figures": {"frames_per_hour": 3000.0, "resolution": [320, 240]}},
    })
    cpu = _run_json("llvm_ad_spectral", "abc", {
        "pbr": {"status": "ok", "figures": {"seconds_to_2pct": 20.0, "variant": "llvm_ad_spectral", "speedup": 0.0}},
        "calibrate": {"status": "ok", "figures": {"seconds_per_case": 300.0}},
        "dataset_rse_0.05": {"status": "ok", "figures": {"frames_per_hour": 200.0, "resolution": [320, 240]}},
        "physical": {"status": "skipped", "figures": {}},
    })
    merged = merge(gpu, cpu)
    assert merged["same_commit"] and merged["commit"] == "abc"
    assert merged["gpu"]["variant"] == "cuda_ad_spectral" and merged["cpu"]["variant"] == "llvm_ad_spectral"
    assert list(merged["benches"]) == ["pbr", "calibrate", "dataset_rse_0.05", "physical"]
    assert merged["benches"]["pbr"]["gpu_over_cpu"] == {"seconds_to_2pct": 0.1}  # no ratio of text or over zero
    assert merged["benches"]["dataset_rse_0.05"]["gpu_over_cpu"] == {"frames_per_hour": 15.0}
    assert merged["benches"]["calibrate"]["gpu_over_cpu"] == {}  # the GPU's failed
    assert merged["benches"]["physical"]["gpu"] is None
    assert merged["benches"]["pbr"]["same_command"] and not merged["benches"]["physical"]["same_command"]
    assert merged["benches"]["calibrate"]["cpu"]["figures"]["seconds_per_case"] == 300.0
    # the merge step, from files
    (tmp_path / "g.json").write_text(json.dumps(gpu))
    (tmp_path / "c.json").write_text(json.dumps({**cpu, "commit": "def"}))
    assert main(["gpu", "merge", str(tmp_path / "g.json"), str(tmp_path / "c.json"), "--json",
                         str(tmp_path / "m.json")]) == 0
    assert json.loads((tmp_path / "m.json").read_text())["same_commit"] is False


def test_figures_follow_dotted_paths():
    result = {"frames_per_hour": 10.0, "local": {"samples": 16, "seconds": None}, "refused": 0}
    assert figures_of(result, "dataset") == {"frames_per_hour": 10.0, "local.samples": 16, "refused": 0}


def test_bad_input_is_refused_before_anything_runs(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(gpu_run, "variant_problem", _forbidden_runner)
    monkeypatch.setattr(gpu_run, "run_command", _forbidden_runner)
    missing = tmp_path / "nowhere" / "gpu.json"
    assert main(["gpu", "run", "--json", str(missing)]) == 1
    assert f"--json {missing}: its folder {missing.parent} does not exist" in capsys.readouterr().err
    assert main(["gpu", "run", "--json", str(tmp_path)]) == 1
    assert "is a folder" in capsys.readouterr().err
    assert main(["gpu", "run", "--json", str(tmp_path / "g.json"), "--cpu-json", str(tmp_path / "no.json")]) == 1
    assert "--cpu-json" in capsys.readouterr().err
    (tmp_path / "bad.json").write_text('{"frames": 1}')
    assert main(["gpu", "run", "--json", str(tmp_path / "g.json"), "--cpu-json", str(tmp_path / "bad.json")]) == 1
    assert "not a run's JSON" in capsys.readouterr().err
    (tmp_path / "merged.json").write_text(json.dumps({"benches": {}, "gpu": {}, "cpu": {}}))
    assert main(["gpu", "run", "--json", str(tmp_path / "g.json"), "--cpu-json", str(tmp_path / "merged.json")]) == 1
    assert "already a merged JSON" in capsys.readouterr().err
    assert main(["gpu", "run", "--json", str(tmp_path / "g.json"), "--only", "nonsense"]) == 1
    assert "--only nonsense: not a bench" in capsys.readouterr().err
    assert main(["gpu", "run", "--json", str(tmp_path / "g.json"), "--rse", "1.5"]) == 1
    assert "--rse must be noise targets in (0, 1), got 1.5" in capsys.readouterr().err
    assert main(["gpu", "merge", str(tmp_path / "no.json"), str(tmp_path / "bad.json"), "--json",
                         str(missing)]) == 1
    assert "does not exist" in capsys.readouterr().err


def test_wheel_folder_that_is_a_file_is_refused(tmp_path, capsys):
    not_a_folder = tmp_path / "wheels"
    not_a_folder.write_text("")
    with pytest.raises(ValueError, match=r"--dir .*wheels exists and is not a folder"):
        gpu_wheels.check_wheel_dir(not_a_folder)
    assert main(["gpu", "wheels", "--dir", str(not_a_folder)]) == 1
    assert "is not a folder" in capsys.readouterr().err


def test_wheel_folder_inside_the_repo_must_be_ignored():
    repo = Path(__file__).resolve().parents[1]
    if not (repo / ".git").exists():
        pytest.skip("not a git checkout")
    gpu_wheels.check_wheel_dir(repo / ".whl", repo)  # the default, ignored
    with pytest.raises(ValueError, match="not git-ignored"):
        gpu_wheels.check_wheel_dir(repo / "pbr_tactile" / "wheels", repo)


def test_plan_sizes_and_budgets():
    benches = plan()
    assert [b.name for b in benches] == ["dataset_rse_0.05", "dataset_rse_0.025", "pbr", "calibrate"]
    assert sum(b.budget_s for b in benches) <= gpu_run.RUN_BUDGET_S
    assert benches[1].budget_s == 2 * benches[0].budget_s
    assert "--target-rse" in benches[1].args and "0.025" in benches[1].args
    assert benches[3].args[:6] == ("calibrate", "benchmark", "--cases", "1", "--taps", "2")
    assert [b.name for b in plan(physical=True, only=["physical", "pbr"])] == ["pbr", "physical"]
    assert [b.name for b in plan(only=["dataset"])] == ["dataset_rse_0.05", "dataset_rse_0.025"]
    assert plan(budget_scale=10)[2].budget_s == 10 * plan()[2].budget_s


def test_repack_drops_members_and_writes_a_valid_record(tmp_path):
    source = tmp_path / "mitsuba-3.9.1-cp312-cp312-manylinux_2_28_x86_64.whl"
    members = {
        "mitsuba/__init__.py": b"x = 1\n",
        "mitsuba/config.py": b"MI_VARIANTS = ['scalar_rgb', 'scalar_spectral']\nOTHER = 1\n",
        "mitsuba/scalar_rgb.cpython-312-x86_64-linux-gnu.so": b"\0" * 100,
        "mitsuba/scalar_spectral.cpython-312-x86_64-linux-gnu.so": b"\1" * 100,
        "mitsuba/cuda_ad_spectral_polarized.cpython-312-x86_64-linux-gnu.so": b"\2" * 100,
        "mitsuba/plugins/sunsky.so": b"sky",
        "mitsuba/plugins/volpath.so": b"vol",
        "mitsuba/include/mitsuba.h": b"h",
        "mitsuba/__init__.pyi": b"stub",
        "mitsuba-3.9.1.dist-info/METADATA": b"Name: mitsuba\n",
        "mitsuba-3.9.1.dist-info/RECORD": b"stale\n",
    }
    with zipfile.ZipFile(source, "w") as z:
        for name, data in members.items():
            z.writestr(name, data)
    target = tmp_path / "out" / source.name
    target.parent.mkdir()
    stats = gpu_wheels.repack(source, target, "mitsuba")
    with zipfile.ZipFile(target) as z:
        names = set(z.namelist())
        assert names == {"mitsuba/__init__.py", "mitsuba/config.py",
                         "mitsuba/scalar_spectral.cpython-312-x86_64-linux-gnu.so", "mitsuba/plugins/volpath.so",
                         "mitsuba-3.9.1.dist-info/METADATA", "mitsuba-3.9.1.dist-info/RECORD"}
        assert all(i.compress_type == zipfile.ZIP_LZMA for i in z.infolist())
        record = z.read("mitsuba-3.9.1.dist-info/RECORD").decode().splitlines()
        assert len(record) == len(names)
        rows = dict((r.split(",")[0], r.split(",", 1)[1]) for r in record)
        assert rows["mitsuba-3.9.1.dist-info/RECORD"] == ","
        assert rows["mitsuba/plugins/volpath.so"] == gpu_wheels._record_hash(b"vol") + ",3"
    assert stats["dropped"] == 5 and stats["members"] == 5


def test_pinned_versions_take_what_is_installed():
    def installed(name):
        if name == "mitsuba":
            return "3.9.2"
        raise gpu_wheels.metadata.PackageNotFoundError(name)

    pins = gpu_wheels.pinned_versions({"mitsuba": "3.9.1", "trimesh": "5.2.0"}, installed)
    assert pins == {"mitsuba": ("3.9.2", "installed here"), "trimesh": ("5.2.0", "default")}
    with pytest.raises(gpu_wheels.WheelError, match="3.9"):
        gpu_wheels.pinned_versions({"mitsuba": "3.9.1"}, lambda name: "3.10.0")


def test_no_plugin_our_scenes_name_is_left_out_of_mitsuba():
    """The slim Mitsuba wheel keeps every plugin type a scene dict of ours names."""
    import re

    repo = Path(__file__).resolve().parents[1]
    named = set()
    for path in list((repo / "pbr_tactile").rglob("*.py")) + list((repo / "studies").rglob("*.py")):
        named |= set(re.findall(r"""["']type["']\s*:\s*["']([a-z_]+)["']""", path.read_text()))
    assert {"ply", "volpath", "homogeneous"} <= named  # the scan finds them
    assert not named & set(gpu_wheels.MITSUBA_UNUSED_PLUGINS)
    for variant in gpu_run.GPU_VARIANT, "llvm_ad_spectral", "scalar_spectral":
        assert not gpu_wheels.dropped("mitsuba", f"mitsuba/{variant}.cpython-312-x86_64-linux-gnu.so")
    assert gpu_wheels.dropped("mitsuba", "mitsuba/llvm_ad_rgb.cpython-312-x86_64-linux-gnu.so")
    assert not gpu_wheels.dropped("mitsuba", "mitsuba/mitsuba_ext.cpython-312-x86_64-linux-gnu.so")
    assert not gpu_wheels.dropped("mitsuba", "mitsuba/data/srgb.coeff")  # the "rgb" spectra need it
