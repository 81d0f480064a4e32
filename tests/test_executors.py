"""Dataset generation on local processes and on Ray: the same samples either way, a
killed Ray run resumes, a two-node cluster shares nothing but Ray's object store, and bad
executor input is refused before any work.

Ray starts in seconds, not milliseconds: the cluster tests share one simulated two-node
cluster (``ray.cluster_utils.Cluster``, one CPU per node), shut down at the module's end.
"""

from __future__ import annotations

import os
import pickle
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from scenes.dataset import load_sample, read_samples

ROOT = Path(__file__).resolve().parents[1]
PHONG = {"field": "plane", "background": "none"}


def _fake():
    """tests/fake_renderer.py, the plugin (importable from ROOT: ``_fake_renderer_importable``)."""
    from tests import fake_renderer

    return fake_renderer


def _phong():
    from phong_reference import plugin

    return plugin



def _protocol(spec, mesh, objects=("sphere", "cone"), taps=6):
    from scenes.protocol import base_protocol

    protocol = base_protocol(spec, mesh, objects)
    return replace(protocol, taps=protocol.taps[:taps])


def _samples(root) -> dict:
    """id -> (record, image, depth) of every sample, every file read back."""
    out = {}
    for record in read_samples(root):
        image, depth = load_sample(root, record, (480, 640))
        out[record["id"]] = (record, image, depth)
    return out


@pytest.fixture(autouse=True)
def _fake_renderer_importable(monkeypatch):
    monkeypatch.syspath_prepend(str(ROOT))


# --- Bad input, refused before any work ----------------------------------------------------


def test_bad_executor_input_is_refused(tmp_path, spec, mesh, monkeypatch):
    from scenes.executors import CONNECT_TIMEOUT_S
    from scenes.generate import generate

    protocol = _protocol(spec, mesh)
    with pytest.raises(ValueError, match=r"executor must be one of \('local', 'ray'\), got 'dask'"):
        generate(tmp_path / "a", spec, protocol, _phong(), executor="dask")
    with pytest.raises(ValueError, match="address is for executor 'ray' only, got address '10.0.0.5:6379' with "
                                         "executor 'local'"):
        generate(tmp_path / "a", spec, protocol, _phong(), address="10.0.0.5:6379")
    pytest.importorskip("ray")
    with pytest.raises(ValueError, match="address must be HOST:PORT of a Ray head, e.g. 10.0.0.5:6379, got 'head'"):
        generate(tmp_path / "a", spec, protocol, _phong(), executor="ray", address="head")
    # Ray itself retries an unreachable head for many minutes; this fails at once: the
    # refusal comes from one TCP probe bounded by the named timeout, and Ray is never asked
    # to connect (no timing: the behaviour that makes it fast is what is checked).
    import ray

    from scenes import executors

    probes = []
    connect = executors.socket.create_connection

    def probe(address, timeout=None, *args, **kwargs):
        probes.append((address, timeout))
        return connect(address, timeout, *args, **kwargs)

    with monkeypatch.context() as patch:
        patch.setattr(executors.socket, "create_connection", probe)
        patch.setattr(ray, "init", lambda *a, **k: pytest.fail("ray.init was called: Ray retries for minutes"))
        with pytest.raises(ValueError, match=rf"address '127.0.0.1:1' cannot be reached within {CONNECT_TIMEOUT_S:g} s "
                                             r".*'ray start --head'"):
            generate(tmp_path / "a", spec, protocol, _phong(), executor="ray", address="127.0.0.1:1")
    assert probes == [(("127.0.0.1", 1), CONNECT_TIMEOUT_S)]
    monkeypatch.setitem(sys.modules, "ray", None)  # as if Ray were not installed
    with pytest.raises(ValueError, match=r"executor 'ray' needs Ray, which is not installed: "
                                         r"pip install 'tactile-sim\[ray\]'"):
        generate(tmp_path / "a", spec, protocol, _phong(), executor="ray")
    assert not (tmp_path / "a").exists()  # refused before any work


def test_cli_refuses_address_without_ray(tmp_path):
    res = subprocess.run([sys.executable, "-m", "scenes.cli", "dataset", "--objects", "sphere", "--address",
                          "10.0.0.5:6379", "--out", str(tmp_path / "a")], check=False, capture_output=True,
                         text=True)
    assert res.returncode == 1 and "address is for executor 'ray' only" in res.stderr


# --- Local processes: the whole plugin interface ---------------------------------------------


def test_local_processes_take_shared_inputs_extra_arrays_and_record_fields(tmp_path, spec, mesh, headless_gl):
    from scenes.generate import generate
    from tests.fake_renderer import shared_array

    out = tmp_path / "ds"
    summary = generate(out, spec, _protocol(spec, mesh, taps=4), _fake(), {}, workers=2, progress=False)
    assert summary["samples"] == 4 and summary["executor"] == "local"
    records = read_samples(out)
    expected_sum = float(np.sum(shared_array(), dtype=np.float64))
    for record in records:
        assert record["shared_sum"] == expected_sum and record["node"] is None
        assert record["pid"] != os.getpid()  # rendered in a pool process
        image, _ = load_sample(out, record, (480, 640))
        linear = np.load(out / record["linear"])
        variance = np.load(out / record["variance"])
        assert record["linear"] == f"linear/{record['id']}.npy" and linear.dtype == np.float32
        assert linear.shape == variance.shape == (480, 640, 3)
        np.testing.assert_allclose(linear / 2, image, atol=0.5 / 255 + 1e-6)  # the PNG is 8-bit
    assert any(np.load(out / r["linear"]).max() > 1.0 for r in records)  # a contact shows
    assert (out / "background.png").exists()


# --- Ray on this machine: killed and resumed --------------------------------------------------


@pytest.mark.slow
def test_ray_generation_killed_midway_resumes_with_nothing_lost_or_duplicated(tmp_path, headless_gl):
    pytest.importorskip("ray")
    out = tmp_path / "ds"
    args = [sys.executable, "-m", "scenes.cli", "dataset", "--protocol", "base", "--objects", "sphere,cone",
            "--executor", "ray", "--workers", "2", "--out", str(out)]
    proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.time() + 120
    while time.time() < deadline and proc.poll() is None:
        path = out / "samples.jsonl"
        if path.exists() and path.read_text().count("\n") >= 4:
            break
        time.sleep(0.05)
    assert proc.poll() is None, "the run finished before it could be killed; make the dataset larger"
    os.killpg(proc.pid, signal.SIGKILL)  # the driver, and the Ray cluster it started
    proc.wait()
    first = read_samples(out)
    assert 4 <= len(first) < 36
    res = subprocess.run(args, check=False, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    samples = _samples(out)
    ids = [r["id"] for r in read_samples(out)]
    assert len(ids) == 36 and len(set(ids)) == 36
    assert ids[: len(first)] == [r["id"] for r in first]  # nothing rewritten
    assert (out / "background.png").exists()
    assert all(depth.shape == (480, 640) for _, _, depth in samples.values())
    assert not list(out.rglob(".*.tmp"))


# --- A simulated two-node cluster --------------------------------------------------------------


@pytest.fixture(scope="module")
def cluster(tmp_path_factory, headless_gl):
    """Two Ray nodes of one CPU each on this machine; the driver is not connected."""
    ray = pytest.importorskip("ray")
    from ray.cluster_utils import Cluster

    with pytest.MonkeyPatch.context() as mp:
        # Raylets, so their workers, inherit this environment: the tests' cache, and
        # the repository on the path for the fake renderer.
        mp.setenv("TACTILE_SIM_CACHE", str(tmp_path_factory.getbasetemp() / "cache"))
        mp.setenv("PYTHONPATH", os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")])))
        nodes = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False})
        try:
            nodes.add_node(num_cpus=1)
            nodes.wait_for_nodes()
            yield nodes
        finally:
            ray.shutdown()
            nodes.shutdown()


def test_ray_gives_the_same_samples_as_local_processes(tmp_path, spec, mesh, cluster):
    from scenes.generate import generate

    protocol = _protocol(spec, mesh)
    generate(tmp_path / "local", spec, protocol, _phong(), PHONG, workers=2, progress=False)
    summary = generate(tmp_path / "ray", spec, protocol, _phong(), PHONG, progress=False, executor="ray",
                       address=cluster.address)
    assert summary["executor"] == "ray" and summary["new"] == 6
    local, on_ray = _samples(tmp_path / "local"), _samples(tmp_path / "ray")
    assert sorted(local) == sorted(on_ray) and len(local) == 6
    for sid, (record, image, depth) in local.items():
        assert on_ray[sid][0] == record
        np.testing.assert_array_equal(on_ray[sid][1], image)
        np.testing.assert_array_equal(on_ray[sid][2], depth)
    assert (tmp_path / "ray" / "background.png").read_bytes() == (tmp_path / "local" / "background.png").read_bytes()


@pytest.mark.slow
def test_two_nodes_share_nothing_but_the_object_store(tmp_path, spec, mesh, cluster, monkeypatch):
    import ray

    from scenes.generate import Job, generate
    from tests.fake_renderer import shared_array

    # Watch what the driver hands to Ray: every task's arguments, and every ray.put.
    submitted, puts = [], []
    real_remote, real_put = ray.remote, ray.put

    def remote(*args, **kwargs):
        def wrap(fn):
            task = real_remote(*args, **kwargs)(fn)

            class Spy:
                def remote(self, *task_args):
                    submitted.append(task_args)
                    return task.remote(*task_args)

            return Spy()

        return wrap

    def put(value):
        puts.append(value)
        return real_put(value)

    monkeypatch.setattr(ray, "remote", remote)
    monkeypatch.setattr(ray, "put", put)
    root = tmp_path / "driver-only" / "ds"
    ray.init(address=cluster.address)  # the caller's own connection: used, and left open
    try:
        with pytest.raises(ValueError, match="already connected to a Ray cluster"):
            generate(root, spec, _protocol(spec, mesh), _fake(), {}, executor="ray", address=cluster.address)
        # each tap waits until taps run on both nodes, so neither can take them all (the
        # folder lies outside tmp_path, which no task argument may name: checked below)
        with tempfile.TemporaryDirectory(prefix="meet-") as folder:
            meet = {"meet": {"folder": folder, "nodes": 2}}
            summary = generate(root, spec, _protocol(spec, mesh, taps=8), _fake(), meet, executor="ray",
                               progress=False)
        assert ray.is_initialized()
    finally:
        ray.shutdown()
    assert summary["new"] == 8
    records = read_samples(root)
    # Both nodes rendered, each with the shared array it got from the object store.
    assert len({r["node"] for r in records}) == 2
    assert {r["shared_sum"] for r in records} == {float(np.sum(shared_array(), dtype=np.float64))}
    assert len(puts) == 1 and np.array_equal(puts[0], shared_array())
    refs = {args[-1] for args in submitted}
    assert len(refs) == 1 and isinstance(refs.pop(), ray.ObjectRef)  # one ObjectRef, never the array
    # Tasks get a job and a tap, never the dataset folder: nothing relies on a shared disk.
    assert len(submitted) == 8 + 1  # the taps and the no-contact image
    for args in submitted:
        assert isinstance(args[0], Job)
        assert str(tmp_path) not in repr(args[:-1]) and str(tmp_path).encode() not in pickle.dumps(args[:-1])
    for record in records:
        assert np.load(root / record["variance"]).shape == (480, 640, 3)
    assert (root / "background.png").exists()
