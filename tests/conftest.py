"""Shared fixtures: the default sensor, its mesh and camera, and the reference data."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from scenes.camera import Camera
from scenes.geometry import membrane_mesh
from scenes.gl import GLPlatformError, choose_gl
from scenes.reference_data import require_reference_dir
from scenes.spec import default_spec

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
