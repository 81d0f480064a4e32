"""Shared fixtures: the default sensor, its mesh and camera, and the reference data."""

from __future__ import annotations

import contextlib
import sys
from pathlib import Path

import numpy as np
import pytest

from scenes.camera import Camera
from scenes.geometry import membrane_mesh
from scenes.gl import GLPlatformError, choose_gl
from scenes.reference_data import require_reference_dir
from scenes.spec_read import default_spec

# MuJoCo reads MUJOCO_GL once, when first imported: choose a headless platform first.
try:
    choose_gl()
except GLPlatformError:
    pass

@pytest.fixture(scope="session")
def reference_dir() -> Path:
    """The authors' published data (beside the repository, never copied into it), or skip."""
    try:
        return require_reference_dir()
    except FileNotFoundError as exc:
        pytest.skip(str(exc))


@pytest.fixture(scope="session")
def mujoco_gl():
    """MuJoCo on a headless GL platform, or skip saying which is missing."""
    try:
        choose_gl()  # before mujoco is imported: it reads MUJOCO_GL once
    except GLPlatformError as exc:
        pytest.skip(str(exc))
    return pytest.importorskip("mujoco", reason="MuJoCo is not installed (pip install '.[mujoco]')")


@pytest.fixture(autouse=True)
def _variant_kept():
    """Every test leaves Mitsuba's variant as it found it. The variant is global, and a render
    asked for on another one (``reference(variant="scalar_spectral")``) leaves that one set:
    the session's ``photon_mi`` tests after it would run on a scalar variant, which the
    photon pass refuses."""
    before = _mitsuba_variant()
    yield
    if before is not None and _mitsuba_variant() != before:
        import mitsuba as mi

        mi.set_variant(before)


def _mitsuba_variant():
    """Mitsuba's variant where Mitsuba is imported already, else None (imports nothing)."""
    mi = sys.modules.get("mitsuba")
    return mi.variant() if mi is not None else None


@pytest.fixture(scope="session")
def photon_mi():
    """Mitsuba on a vectorised variant (llvm_ or cuda_), which the photon pass needs, or skip."""
    pytest.importorskip("mitsuba", reason="Mitsuba 3 is not installed (pip install '.[pbr]')")
    from pbr_tactile.variant import VariantError, choose_variant

    try:
        variant = choose_variant().variant()
    except VariantError as exc:
        pytest.skip(str(exc))
    if not variant.startswith(("llvm_", "cuda_")):
        pytest.skip("the photon estimator needs a vectorised variant (apt-get install libllvm19)")
    import mitsuba as mi

    mi.set_variant(variant)
    return mi


@contextlib.contextmanager
def switched_variant(name: str):
    """Mitsuba on variant ``name`` inside the block; the variant set before it is set again
    after it. Mitsuba's variant is global: a test that left it switched would run every
    later test of ``photon_mi`` on that variant (the photon pass refuses a scalar one)."""
    import mitsuba as mi

    from pbr_tactile.variant import choose_variant

    before = mi.variant()  # None when none was set yet: Mitsuba has no unset, and every user sets its own
    try:
        yield choose_variant(name)
    finally:
        if before is not None:
            mi.set_variant(before)


@pytest.fixture
def scalar_mi():
    """Mitsuba on ``scalar_spectral`` for one test (``switched_variant``), or skip."""
    pytest.importorskip("mitsuba", reason="Mitsuba 3 is not installed (pip install '.[pbr]')")
    with switched_variant("scalar_spectral") as mi:
        yield mi


@pytest.fixture(scope="session")
def spec():
    return default_spec()


@pytest.fixture(scope="session")
def mesh(spec):
    return membrane_mesh(spec)


@pytest.fixture(scope="session")
def camera(spec):
    return Camera.from_spec(spec)


@pytest.fixture(scope="session")
def small_camera(camera):
    """The default camera at 160x120, for fast tests."""
    return camera.scaled(160, 120)


@pytest.fixture(scope="session")
def ref(mesh, camera):
    """The default sensor's no-contact depth D_ref, ray cast from its mesh."""
    from scenes.camera import reference_depth

    return reference_depth(mesh, camera)[0]


@pytest.fixture(scope="session")
def pressed(mesh, camera, ref):
    """A 4 mm sphere pressed 1.5 mm into the membrane where the camera sees pixel (350, 220)."""
    import trimesh

    from scenes.contact import press

    return press(ref, camera, mesh, trimesh.primitives.Sphere(radius=0.004), (350, 220), 0.0015)


@pytest.fixture(scope="session")
def headless_gl():
    """Skip, saying why, unless MuJoCo and a headless GL platform are here."""
    pytest.importorskip("mujoco", reason="MuJoCo is not installed (pip install '.[mujoco]')")
    try:
        choose_gl()
    except GLPlatformError as exc:
        pytest.skip(str(exc))


@pytest.fixture(autouse=True)
def _isolated_cache(tmp_path_factory, monkeypatch):
    """Tests never read or write the user's cache."""
    monkeypatch.setenv("TACTILE_SIM_CACHE", str(tmp_path_factory.getbasetemp() / "cache"))


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


# --- A tiny capture of the rig, and what replay, compare and diagnose make of it -------------
# Session-scoped, so that test_replay, test_compare and test_reports_browser share one set of
# renders (about ten seconds in all). They run outside the function-scoped cache isolation
# above, so they isolate the cache (and find tests.fake_*) themselves.

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def session_env(tmp_path_factory):
    """Headless MuJoCo (or skip, saying why), the tests' cache, and the repository on sys.path."""
    pytest.importorskip("mujoco", reason="MuJoCo is not installed (pip install '.[mujoco]')")
    try:
        choose_gl()
    except GLPlatformError as exc:
        pytest.skip(str(exc))
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("TACTILE_SIM_CACHE", str(tmp_path_factory.getbasetemp() / "cache"))
        mp.syspath_prepend(str(ROOT))
        yield


@pytest.fixture(scope="session")
def tiny_spec(session_env, spec):
    """The default sensor at 80x60 (tests/fake_capture.py)."""
    from tests.fake_capture import tiny_spec as scaled

    return scaled(spec)


@pytest.fixture(scope="session")
def tiny_capture(session_env, tiny_spec, tmp_path_factory) -> Path:
    """A capture of four taps (tests/fake_capture.py) by the fast path (plane field, solid
    background) at 80x60, its measured poses the commanded ones."""
    from tests.fake_capture import capture_protocol, write_capture

    protocol = capture_protocol(tiny_spec, membrane_mesh(tiny_spec))
    return write_capture(tmp_path_factory.mktemp("capture") / "capture", tiny_spec, protocol)


@pytest.fixture(scope="session")
def tiny_replay(tiny_capture, tmp_path_factory) -> Path:
    """``tactile-sim dataset --replay`` of tiny_capture with the capture's own settings."""
    from scenes.cli import main

    out = tmp_path_factory.mktemp("replay") / "sim"
    assert main(["dataset", "--replay", str(tiny_capture), "--renderer", "phong", "--field", "plane",
                 "--background", "solid", "--workers", "1", "--out", str(out)]) == 0
    return out


@pytest.fixture(scope="session")
def compare_result(tiny_capture, tmp_path_factory) -> tuple[dict, Path]:
    """(table.json, folder) of a comparison of tiny_capture: two fields, every background,
    and tests/fake_renderer.py standing in for the slow reference on two taps."""
    from studies.compare.run import compare
    from tests import fake_renderer

    out = tmp_path_factory.mktemp("compare") / "table"
    result = compare(tiny_capture, out, fields=("plane", "linear"), reference_taps=2, reference_renderer=fake_renderer,
                     reference_label="tests.fake_renderer", bootstrap=200, seed=1, progress=False)
    return result, out


@pytest.fixture(scope="session")
def diagnose_report(tiny_capture, tiny_replay, tmp_path_factory) -> Path:
    """The folder of ``tactile-sim diagnose CAPTURE REPLAY`` (one effect, to be quick)."""
    from scenes.cli import main

    out = tmp_path_factory.mktemp("diagnose") / "report"
    assert main(["diagnose", str(tiny_capture), str(tiny_replay), "--out", str(out), "--quiet",
                 "--effects", "camera_response"]) == 0
    return out


@pytest.fixture(scope="session")
def absolute_imports():
    """A function: the modules a source file imports, failing on a relative import (the
    gap benchmark's generators must be written apart from the diagnosis)."""
    import ast

    def read(path: Path) -> list[str]:
        names = []
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ImportFrom):
                assert node.level == 0, f"relative import in {path.name}: {ast.dump(node)}"
                names.append(node.module)
            elif isinstance(node, ast.Import):
                names += [a.name for a in node.names]
        return names

    return read
